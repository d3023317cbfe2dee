"""The closed-loop protocol :func:`wmrjax.simulate` runs: an abstract base that declares every hook
a system may have, each with its default (a leaf module: the controllers, the plant and
sampled-data loops, the run and the resource model all read the same declarations).

A system is a static, hashable object (a frozen dataclass): its arrays are in ``params``.
"""

from __future__ import annotations

import abc
from typing import Any, Callable

__all__ = ["ClosedLoop"]


class ClosedLoop(abc.ABC):
    """What :func:`wmrjax.simulate` integrates: ``dz/dt = vector_field(t, z, params)[0]``.

    ``z`` and ``dz/dt`` share one pytree structure; integer leaves are discrete state, held by
    the integrator. Subclasses override the hooks they need; the defaults say "none".

    Attributes:
      n_state: size of the flattened state (None: not checked against ``z0``).
      state_names: one name per flattened state component (for messages).
      sample_every: RK4 steps per controller period of a sampled-data loop, whose
        :meth:`sample` runs at the start of every period (None: a continuous loop).
      post_step: ``post_step(t, z, params) -> z``, a discrete transition after every step
        (a hybrid loop's mode switch), or None. A loop is hybrid or sampled, not both.
      final_report: ``final_report(t, z, params) -> pytree``, a report of the final state kept
        in the run's diagnostics (a static law's internal dynamics), or None.
    """

    n_state: int | None = None
    state_names: tuple = ()
    sample_every: int | None = None
    post_step: Callable | None = None
    final_report: Callable | None = None

    @abc.abstractmethod
    def vector_field(self, t, z, params: Any) -> tuple[Any, Any]:
        """``(dz/dt, aux)`` at time ``t`` [s]: ``aux`` carries ``control`` and ``regularity``."""

    def sample(self, k, t, z, params: Any):
        """A sampled-data loop's controller at the start of period ``k``: the state with the new
        held command. Only called when :attr:`sample_every` is set."""
        raise NotImplementedError(f"{type(self).__name__} is not a sampled-data loop (sample_every is None)")

    def held(self, z):
        """A sampled-data loop's state as a pytree of booleans: True for the leaves held between
        samples (the command, the controller's state), which the integrator leaves alone over a
        period. Only called when :attr:`sample_every` is set."""
        raise NotImplementedError(f"{type(self).__name__} is not a sampled-data loop (sample_every is None)")

    def check_run(self, params: Any, *, t0, dt, n_steps: int) -> None:
        """Refuse (ValueError) a run these parameters cannot make, before anything compiles
        (default: nothing to check)."""

    def law_state(self, z):
        """The control law's own state ``(X, compensator...)`` within the loop's state ``z``
        (batched or not); the default: the whole state."""
        return z

    def reference_jet_floats(self) -> int:
        """Numbers per time the system's reference check holds (its outputs' jets up to the
        relative degree), for the memory model; 0: no reference check."""
        return 0
