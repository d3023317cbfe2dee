"""Feedback-linearizing controllers of d'Andrea-Novel, Campion & Bastin (1995).

* :mod:`~wmrjax.controllers.law` -- the closed-loop protocol and the one generic law;
* :mod:`~wmrjax.controllers.dynamic` -- Table 4 (dynamic linearization, posture tracking);
* :mod:`~wmrjax.controllers.static` -- Prop 3 and Table 3 (static linearization);
* :mod:`~wmrjax.controllers.hybrid` -- §6.2 (tracking, then a time-varying stabilizer);
* :mod:`~wmrjax.controllers.plant` -- a law closed around a saturating, mismatched plant;
* :mod:`~wmrjax.controllers.sampled` -- the same, run by a digital controller (sample, hold, noise);
* :mod:`~wmrjax.controllers.placement` -- the one placement of an initial state near a reference.
"""

from wmrjax.controllers.dynamic import TABLE4, DynamicLinearization, DynamicParams, Table4Row, dynamic_linearization
from wmrjax.controllers.hybrid import Hybrid, HybridParams, HybridState, TimeVarying, hybrid_parking, stabilizer
from wmrjax.controllers.law import DET_FLOOR, Aux, Extension, Level, LinearizingController, LinearizingLaw, Task
from wmrjax.controllers.placement import Space, initial_keys, place
from wmrjax.controllers.plant import PlantLoop, PlantParams, with_plant
from wmrjax.controllers.sampled import SampledLoop, SampledParams, SampledState, measurement_noise, sampled
from wmrjax.controllers.static import (
    TABLE3,
    InternalDynamics,
    StaticLinearization,
    StaticParams,
    Steering,
    Table3Row,
    controller,
    static_linearization,
    steering_constant,
)
from wmrjax.system import ClosedLoop

__all__ = [
    "TABLE4",
    "DynamicLinearization",
    "DynamicParams",
    "Table4Row",
    "dynamic_linearization",
    "Hybrid",
    "HybridParams",
    "HybridState",
    "TimeVarying",
    "hybrid_parking",
    "stabilizer",
    "DET_FLOOR",
    "Aux",
    "Extension",
    "Level",
    "LinearizingController",
    "LinearizingLaw",
    "Task",
    "Space",
    "initial_keys",
    "place",
    "PlantLoop",
    "PlantParams",
    "with_plant",
    "SampledLoop",
    "SampledParams",
    "SampledState",
    "measurement_noise",
    "sampled",
    "TABLE3",
    "InternalDynamics",
    "StaticLinearization",
    "StaticParams",
    "Steering",
    "Table3Row",
    "controller",
    "static_linearization",
    "steering_constant",
    "ClosedLoop",
]
