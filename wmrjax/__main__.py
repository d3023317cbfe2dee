"""``python -m wmrjax JOB ...``: the ``wmrjax`` command (:mod:`wmrjax.cli`)."""

import sys

from wmrjax.cli import main

if __name__ == "__main__":
    sys.exit(main())
