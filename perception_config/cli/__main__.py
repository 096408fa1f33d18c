"""`python -m perception_config.cli ...`: the same as `perception-config ...`."""
import sys

from . import main

sys.exit(main())
