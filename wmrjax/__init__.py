"""wmrjax: wheeled mobile robots under feedback-linearizing control, in JAX.

Implements d'Andrea-Novel, Campion & Bastin, "Control of nonholonomic wheeled mobile
robots by state feedback linearization", IJRR 14(6), 1995. Float64 is not enabled on
import; call ``jax.config.update("jax_enable_x64", True)`` in your entry point.
"""

from wmrjax import autodiff, certify, controllers, export, io, linearize, references, resources, robots, xla_cpu  # noqa: F401
from wmrjax._rk4 import rk4_step  # noqa: F401
from wmrjax.autodiff import batch_value_and_grad, value_and_grad  # noqa: F401
from wmrjax.controllers import (  # noqa: F401
    Aux,
    ClosedLoop,
    DynamicLinearization,
    HybridState,
    InternalDynamics,
    Level,
    PlantLoop,
    PlantParams,
    SampledLoop,
    SampledParams,
    SampledState,
    StaticLinearization,
    Task,
    controller,
    dynamic_linearization,
    hybrid_parking,
    measurement_noise,
    sampled,
    static_linearization,
    with_plant,
)
from wmrjax.gains import Gains, GainSchedule  # noqa: F401
from wmrjax.references import Reference  # noqa: F401
from wmrjax.robots import Geometry, RobotType, robot_type  # noqa: F401
from wmrjax.simulate import (  # noqa: F401
    Diagnostics,
    Trajectory,
    batch_map,
    batch_mesh,
    scalar_parts,
    scalarized,
    shard_batch,
    simulate,
)
from wmrjax.xla_cpu import configure_cpu, cpu_flags  # noqa: F401

__version__ = "0.2.0"
