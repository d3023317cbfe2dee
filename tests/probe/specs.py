"""Small problem files and data the cases write into their directories: every one runs in a
few seconds on a laptop core (the probe of one tree stays within minutes)."""

import math

# a sweep of 18 runs of 100 RK4 steps in 5 blocks (the sweep tests' file)
SWEEP = """title = "probe"
[controller]
law = "dynamic"
robot = "(2,0)"
level = "velocity"
[geometry]
e = 0.0
[reference]
family = "circle"
options = { radius = [2.0, 3.0], omega = 0.5 }
[initial]
space = "output"
x = [-0.5, 0.0, 0.7]
y = { min = -1.0, max = 1.0, num = 3 }
[gains]
poles = POLES
[simulation]
t_final = 2.0
dt = 0.02
block = 4
"""


def sweep(poles: float = 1.0, changes=()) -> str:
    """The small sweep with its gains' poles, and ``(old, new)`` text replacements."""
    text = SWEEP.replace("POLES", repr(float(poles)))
    for old, new in changes:
        assert old in text, old
        text = text.replace(old, new)
    return text


# a slower sweep: one run per block, 40 s horizons (time to kill it between blocks)
SLOW_SWEEP = sweep(changes=[("t_final = 2.0", "t_final = 40.0"), ("block = 4", "block = 1")])

# a static point law: |det K| = |e sin(delta)| is the same for every run
STATIC_POINT_SWEEP = """title = "static_point"
[controller]
law = "static"
robot = "(2,0)"
level = "torque"
task = "point"
[geometry]
e = 0.3
delta = 1.5707963267948966
[reference]
family = "circle"
[initial]
space = "physical"
x = [0.0, 0.2]
[gains]
poles = 1.0
[simulation]
t_final = 1.0
dt = 0.02
"""

# a tuning problem without a certificate (a static law): a short one, for the probe's cases
TUNE = """title = "probe_tune"
[controller]
law = "static"
robot = "(3,0)"
task = "posture"
[plant]
control_period = 0.05
[reference]
family = "line"
[initial]
space = "physical"
random = { count = 4, seed = 0 }
x = { low = -0.5, high = 0.5 }
y = { low = -0.5, high = 0.5 }
[gains]
poles = 1.0
[simulation]
t_final = 1.0
dt = 0.05
[tune]
steps = 4
[tune.scenarios]
train = 2
validation = 2
heldout = 2
[tune.stopping]
eval_every = 2
[tune.baselines]
seeds = 1
cma_population = 2
"""

# the same problem as a dict, for the library's tuner (wmrjax.tune.tune) in a snippet
TUNE_DICT = {
    "controller": {"law": "static", "robot": "(3,0)", "task": "posture"},
    "plant": {"control_period": 0.05},
    "reference": {"family": "line"},
    "initial": {
        "space": "physical",
        "random": {"count": 4, "seed": 0},
        "x": {"low": -0.5, "high": 0.5},
        "y": {"low": -0.5, "high": 0.5},
    },
    "gains": {"poles": 1.0},
    "simulation": {"t_final": 1.0, "dt": 0.05},
    "tune": {"steps": 4, "scenarios": {"train": 2, "validation": 2, "heldout": 2}, "stopping": {"eval_every": 2}},
}

# the options that make the shipped section_6_1 tuning problem small
TUNE_SMALL = (
    *("--set", "tune.steps=2", "--set", "tune.scenarios.train=2", "--set", "tune.scenarios.validation=2"),
    *("--set", "tune.scenarios.heldout=2", "--set", "tune.baselines.seeds=1", "--set", "tune.baselines.budget=1"),
    *("--set", "tune.baselines.cma_population=2"),
)

# the certification with small counts and no falsifier (its shortest run)
CERTIFY_SMALL = (
    *("--set", "certify.n_starts=0", "--set", "certify.n_empirical=8", "--set", "certify.n_directions=4"),
    *("--set", "certify.map_grid=2"),
)


def circle_csv(t0: float = 0.0, t1: float = 4.0, n: int = 81, header: str = "t,x,y", sep: str = ",") -> str:
    """Samples of the circle of radius 2 m at 0.5 rad/s (the probe's sampled path) as CSV text."""
    rows = [header]
    for i in range(n):
        t = t0 + (t1 - t0) * i / (n - 1)
        rows.append(sep.join(repr(v) for v in (t, 2.0 * math.cos(0.5 * t), 2.0 * math.sin(0.5 * t))))
    return "\n".join(rows) + "\n"


def gains_json(robot: str, level: str, law: str, coefficients) -> str:
    """A tuned-gains file as ``wmrjax tune`` writes it (kind, robot, level, law, coefficients)."""
    import json

    poles = [[[-c, 0.0] for c in row] for row in coefficients] if all(len(r) == 1 for r in coefficients) else None
    return json.dumps(
        {
            "kind": "wmrjax.gains",
            "robot": robot,
            "level": level,
            "law": law,
            "coefficients": coefficients,
            "poles_re_im": poles,
        },
        indent=2,
    )


# a samples-family sweep over a CSV file (written next to it)
SAMPLES_SWEEP = """title = "samples"
[controller]
law = "dynamic"
robot = "(2,0)"
level = "velocity"
[geometry]
e = 0.0
[reference]
family = "samples"
file = "circle.csv"
[initial]
space = "output"
x = [-0.1, 0.0, 0.1]
y = [-0.1, 0.1]
[simulation]
t_final = T_FINAL
dt = 0.02
"""
