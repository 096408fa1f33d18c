"""`perception-config bench blocks | convergence | real | generators`: benchmarks of the building
blocks, on one core."""
from __future__ import annotations

import argparse
from pathlib import Path

from .args import add_dataset_args, one_core


def _cmd_bench_blocks(args: argparse.Namespace) -> int:
    one_core()
    from ..bench.blocks import bench_blocks, format_blocks
    from ..blocks.pipeline import load_pipeline
    from ..datasets.bop_json import save_json

    stats = bench_blocks(args.dataset, load_pipeline(args.pipeline), n_frames=args.frames, lam=args.noise_lambda,
                         split=args.split, progress=not args.quiet, use_depth=args.use_depth)
    save_json(args.out, stats)
    print(format_blocks(stats))
    print(f"wrote {args.out}")
    return 0


def _cmd_bench_convergence(args: argparse.Namespace) -> int:
    one_core()
    from ..bench.blocks import convergence_table, format_convergence
    from ..blocks.pipeline import load_pipeline
    from ..datasets.bop_json import save_json

    lambdas = [float(x) for x in args.lambdas.split(",")]
    table = convergence_table(args.dataset, load_pipeline(args.pipeline), lambdas, n_frames=args.frames,
                              max_applications=args.applications, split=args.split, progress=not args.quiet,
                              use_depth=args.use_depth)
    save_json(args.out, table)
    print(format_convergence(table))
    print(f"wrote {args.out}")
    return 0


def _cmd_bench_real(args: argparse.Namespace) -> int:
    one_core()
    from ..bench.real import bench_real, format_real, save_real
    from ..blocks.pipeline import load_pipeline

    result = bench_real(args.dataset, load_pipeline(args.pipeline), n_frames=args.frames, seeds=args.seeds,
                        lambdas=[float(x) for x in args.lambdas.split(",")], max_calls=args.calls,
                        min_visib=args.min_visib, seed=args.seed, split=args.split, progress=not args.quiet,
                        blocks=args.blocks.split(",") if args.blocks else None,
                        refiner_costs=not args.no_refiner_costs, use_depth=args.use_depth)
    paths = save_real(result, args.out)
    print(format_real(result))
    print(f"wrote {paths[0]} and {paths[1]}")
    return 0


def _cmd_bench_generators(args: argparse.Namespace) -> int:
    one_core()
    from ..bench.generators import bench_generators, format_generators, save_generators
    from ..blocks.pipeline import load_pipeline

    generators = [g for g in args.generators.split(",") if g]
    if not generators:
        raise ValueError("--generators: name at least one generation block")
    result = bench_generators(args.dataset, generators, load_pipeline(args.pipeline) if args.pipeline else None,
                              n_frames=args.frames, min_visib=args.min_visib, confident=args.confident,
                              split=args.split, use_depth=args.use_depth, seed=args.seed, verifier=args.verifier,
                              progress=not args.quiet)
    paths = save_generators(result, args.out)
    print(format_generators(result))
    print(f"wrote {paths[0]} and {paths[1]}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    be = sub.add_parser("bench", help="benchmarks of the building blocks (one core)")
    besub = be.add_subparsers(dest="bench_command", required=True)
    for name, func, helptext in (
        ("blocks", _cmd_bench_blocks, "median/p90 ms per call of every block"),
        ("convergence", _cmd_bench_convergence, "share of successful picks per refiner and lambda"),
    ):
        c = besub.add_parser(name, help=helptext)
        add_dataset_args(c)
        c.add_argument("--out", type=Path, required=True, help="JSON output file")
        c.add_argument("--pipeline", type=Path, default=None,
                       help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                            "(default: default)")
        c.add_argument("--frames", type=int, default=10, help="number of images to use")
        c.add_argument("--split", default="test")
        c.add_argument("--quiet", action="store_true")
        c.set_defaults(func=func)
        if name == "blocks":
            c.add_argument("--noise-lambda", type=float, default=0.2, help="noise of the benchmarked hypotheses")
        else:
            c.add_argument("--lambdas", default="0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0")
            c.add_argument("--applications", type=int, default=5, help="max applications of the refiner")
    c = besub.add_parser("real", help="refiners and scores on a BOP dataset's frames (with or without depth)")
    add_dataset_args(c)
    c.add_argument("--out", type=Path, required=True, help="folder for real.json and real.png, or a .json file")
    c.add_argument("--pipeline", type=Path, default=None,
                   help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                        "(default: default)")
    c.add_argument("--frames", type=int, default=None, help="number of images to use (default: all)")
    c.add_argument("--seeds", type=int, default=5, help="perturbations per object and lambda")
    c.add_argument("--lambdas", default="0,0.1,0.3", help="starting noise levels of the refiners (0 = ground truth)")
    c.add_argument("--calls", type=int, default=3, help="successive calls of a refiner")
    c.add_argument("--min-visib", type=float, default=0.3, help="smallest visib_fract of an object")
    c.add_argument("--blocks", default=None, help="comma-separated action / block names (default: all)")
    c.add_argument("--no-refiner-costs", action="store_true", help="do not rank the refiners' own costs as scores")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--split", default="test")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=_cmd_bench_real)
    c = besub.add_parser("generators", help="the generators' ranked candidates against the annotations: top-1, "
                                            "top-5 and confident wrong, per object, with declared and derived "
                                            "symmetries")
    add_dataset_args(c)
    c.add_argument("--out", type=Path, required=True,
                   help="folder for generators.json and generators.png, or a .json file")
    c.add_argument("--generators", default="resting_pose,ppf,global_registration",
                   help="comma-separated generation blocks (default: the cell's three)")
    c.add_argument("--pipeline", default=None,
                   help="run each generator with the parameters this pipeline gives it (YAML, or a shipped name, "
                        "e.g. cell); default: the blocks' own defaults")
    c.add_argument("--frames", type=int, default=None, help="number of images to use (default: all)")
    c.add_argument("--min-visib", type=float, default=0.0, help="smallest visib_fract of an object")
    c.add_argument("--confident", type=float, default=0.5,
                   help="a first candidate's confidence from which a wrong answer counts as confidently wrong")
    c.add_argument("--verifier", default=None, metavar="MODEL",
                   help="also score every candidate with this pick-success model ('shipped', or a fit-score folder): "
                        "its AUC, Brier and calibration error on the candidates, and the answers ranked by it")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--split", default="test")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=_cmd_bench_generators)
