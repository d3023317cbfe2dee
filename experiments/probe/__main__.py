"""``python -m experiments.probe --tree DIR --out OUT``: probe a wmrjax checkout (see docs/experiments/probe.md)."""

import sys

from experiments.probe.cli import main

sys.exit(main())
