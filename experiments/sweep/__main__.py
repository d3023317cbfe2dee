"""``python -m experiments.sweep SPEC.toml --out DIR``: run a sweep file (see docs/problem_files.md)."""

import sys

from experiments.sweep.cli import main

sys.exit(main())
