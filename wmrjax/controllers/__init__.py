"""Feedback-linearizing controllers of d'Andrea-Novel, Campion & Bastin (1995)."""

from wmrjax.controllers.dynamic import (  # noqa: F401
    EXTENSIONS,
    DynamicExtension,
    DynamicLinearization,
    DynamicParams,
    Gains,
    dynamic_linearization,
)
from wmrjax.controllers.hybrid import Hybrid, HybridParams, TimeVarying, hybrid_parking, stabilizer  # noqa: F401
from wmrjax.controllers.static import (  # noqa: F401
    StaticLinearization,
    StaticParams,
    Steering,
    controller,
    static_linearization,
    steering_constant,
)
