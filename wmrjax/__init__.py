"""wmrjax: wheeled mobile robots under feedback-linearizing control, in JAX.

Implements d'Andrea-Novel, Campion & Bastin, "Control of nonholonomic wheeled mobile
robots by state feedback linearization", IJRR 14(6), 1995. Float64 is not enabled on
import; call ``jax.config.update("jax_enable_x64", True)`` in your entry point.
"""

from wmrjax import autodiff, certify, controllers, export, io, linearize, references, resources, robots, xla_cpu
from wmrjax._rk4 import rk4_step
from wmrjax.autodiff import batch_value_and_grad, value_and_grad
from wmrjax.controllers import (
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
from wmrjax.gains import Gains, GainSchedule
from wmrjax.references import Reference
from wmrjax.robots import Geometry, RobotType, robot_type
from wmrjax.simulate import (
    Diagnostics,
    Trajectory,
    batch_map,
    batch_mesh,
    scalar_parts,
    scalarized,
    shard_batch,
    simulate,
)
from wmrjax.xla_cpu import configure_cpu, cpu_flags

__all__ = [
    "autodiff",
    "certify",
    "controllers",
    "export",
    "io",
    "linearize",
    "references",
    "resources",
    "robots",
    "xla_cpu",
    "rk4_step",
    "batch_value_and_grad",
    "value_and_grad",
    "Aux",
    "ClosedLoop",
    "DynamicLinearization",
    "HybridState",
    "InternalDynamics",
    "Level",
    "PlantLoop",
    "PlantParams",
    "SampledLoop",
    "SampledParams",
    "SampledState",
    "StaticLinearization",
    "Task",
    "controller",
    "dynamic_linearization",
    "hybrid_parking",
    "measurement_noise",
    "sampled",
    "static_linearization",
    "with_plant",
    "Gains",
    "GainSchedule",
    "Reference",
    "Geometry",
    "RobotType",
    "robot_type",
    "Diagnostics",
    "Trajectory",
    "batch_map",
    "batch_mesh",
    "scalar_parts",
    "scalarized",
    "shard_batch",
    "simulate",
    "configure_cpu",
    "cpu_flags",
]

__version__ = "0.2.0"
