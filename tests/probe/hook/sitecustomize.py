"""Loaded by Python at start-up in every process of a probe case (this directory is on its
``PYTHONPATH``): installs the spy on JAX's time loops (:mod:`probe_hook`)."""

import probe_hook

probe_hook.install()
