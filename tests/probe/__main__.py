"""``python -m tests.probe --tree DIR --out OUT``: probe a wmrjax checkout (see docs/commands/probe.md)."""

import sys

from tests.probe.cli import main

sys.exit(main())
