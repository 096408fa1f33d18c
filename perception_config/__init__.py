"""perception_config: a ROS 2 perception service for robotic picking that configures itself."""

__version__ = "0.1.0"

import os as _os

# Our numpy work is many small products (Nx3 @ 3x3): OpenBLAS threads only add contention on
# the 2-core machines this runs on (measured up to 50x slower under load). A user's setting wins.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _defer_open3d_plotly() -> None:
    """`import open3d` imports plotly and dash for open3d.visualization.draw_plotly, about half of
    its import time (0.4 s of CPU in every node process and worker); this package never draws with
    plotly. A stand-in module takes its place, and loads the real one when one of its functions is
    called (or any other name of it is looked up): the same functions, on first use."""
    import importlib.machinery
    import importlib.util
    import sys

    name = "open3d.visualization.draw_plotly"
    if "open3d" in sys.modules or name in sys.modules:
        return

    class DeferredPlotly:
        @staticmethod
        def find_spec(fullname, path, target=None):
            return importlib.machinery.ModuleSpec(name, DeferredPlotly) if fullname == name else None

        @staticmethod
        def create_module(spec):
            return None

        @staticmethod
        def exec_module(module):
            real = []

            def load():
                if not real:
                    spec = importlib.machinery.PathFinder.find_spec(name, sys.modules["open3d.visualization"].__path__)
                    real.append(importlib.util.module_from_spec(spec))
                    spec.loader.exec_module(real[0])
                    sys.modules[name] = real[0]
                return real[0]

            def deferred(function):
                def call(*args, **kwargs):
                    return getattr(load(), function)(*args, **kwargs)
                call.__name__ = call.__qualname__ = function
                return call

            for function in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
                setattr(module, function, deferred(function))

            def getattr_(attr):
                if attr.startswith("__"):  # the import system asks for __path__ and the like
                    raise AttributeError(attr)
                return getattr(load(), attr)

            module.__getattr__ = getattr_
            sys.meta_path.remove(DeferredPlotly)

    sys.meta_path.insert(0, DeferredPlotly)


_defer_open3d_plotly()
