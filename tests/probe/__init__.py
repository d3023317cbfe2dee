"""A reproducible probe of bad and hostile inputs (issue 34): ``python -m tests.probe --tree DIR --out OUT``.

* :mod:`tests.probe.harness` -- a case, its run in a fresh process against any checkout
  (the tree first on ``PYTHONPATH``), the outcome;
* :mod:`tests.probe.oracles` -- the shapes of "what a user should see" (GOOD, POOR, BAD);
* ``cases_*`` -- the cases by category (data loss, wrong answers, resources, late or unclear
  refusals, user files), each with its own oracle;
* ``hook/`` -- what runs inside a case's process (a spy on JAX's time loops, the snippet runner,
  the drivers' helpers); standard library only;
* :mod:`tests.probe.cli` -- the command line, ``OUT/summary.json`` and ``OUT/cases.md``.
"""
