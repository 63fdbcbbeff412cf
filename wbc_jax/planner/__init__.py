"""Planner: reference generators, jit- and vmap-able (plans are built once, on the host).

- :mod:`.spline`: piecewise cubic paths (object / CoM references), cubic segments.
- :mod:`.gait`: trot scheduler (which feet swing, phases, times to liftoff/touchdown).
- :mod:`.swing`: swing-foot references (two splines per swing), footholds, quintics.
- :mod:`.zmp`: cart-table ZMP, support-polygon margin and clamping for CoM replanning.
- :mod:`.capture_point`: LIPM capture-point walking pattern (centroidal paper).
- :mod:`.transport`: the transport task's plan (object path, CoM, footholds) and its per-step reference;
  :mod:`.scene_geometry` (obstacles, terrain, leg geometry) and :mod:`.apf` (the object's path over obstacles).

Conventions: world z up; feet ordered FL, FR, BL, BR (0..3); trot pairs (FL, BR) and
(FR, BL), (FL, BR) swings first; heading = yaw of the walking direction (the transport
scene walks along -y: heading -pi/2).
"""

from .capture_point import (
    CPReference,
    TrotFootsteps,
    cp,
    cp_rate,
    cp_reference,
    cp_trajectory,
    desired_com_velocity,
    end_of_step_cps,
    first_footstep_for_rest,
    footstep_plan_trot,
    initial_cps,
    omega,
)
from .gait import (
    BL,
    BR,
    FL,
    FOOT_NAMES,
    FOOT_PAIR,
    FR,
    PAIRS,
    GaitParams,
    GaitState,
    foot_stance_time,
    gait_phase,
    half_cycle,
    t_stop_after,
)
from .spline import (
    CubicPath,
    cubic_hermite,
    cubic_path,
    eval_cubic,
    eval_path,
    max_abs_accel_z,
    offset_path,
    pad_path,
    path_end_time,
    poly_eval,
    straight_path,
    waypoint_times,
)
from .swing import quintic, raibert_foothold, swing_reference
from .zmp import clamp_to_support, min_zmp_margin, preview_com_xy, replan_com, support_margin, zmp_xy

__all__ = [
    "BL",
    "BR",
    "FL",
    "FOOT_NAMES",
    "FOOT_PAIR",
    "FR",
    "PAIRS",
    "CPReference",
    "CubicPath",
    "GaitParams",
    "GaitState",
    "TrotFootsteps",
    "clamp_to_support",
    "cp",
    "cp_rate",
    "cp_reference",
    "cp_trajectory",
    "cubic_hermite",
    "cubic_path",
    "desired_com_velocity",
    "end_of_step_cps",
    "eval_cubic",
    "eval_path",
    "first_footstep_for_rest",
    "foot_stance_time",
    "footstep_plan_trot",
    "gait_phase",
    "half_cycle",
    "initial_cps",
    "max_abs_accel_z",
    "min_zmp_margin",
    "offset_path",
    "omega",
    "pad_path",
    "path_end_time",
    "poly_eval",
    "preview_com_xy",
    "quintic",
    "raibert_foothold",
    "replan_com",
    "straight_path",
    "support_margin",
    "swing_reference",
    "t_stop_after",
    "waypoint_times",
    "zmp_xy",
]
