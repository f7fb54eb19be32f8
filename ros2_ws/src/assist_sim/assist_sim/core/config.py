"""Simulation settings as dataclasses (one place for every constant of the world)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Mapping

import yaml

from assist_common.touchdown import TouchdownConfig

from .arducopter import ArduCopterConfig


@dataclass
class SceneConfig:
    """Scene generator: five pads in a row along +x (paper, 'CM-VAE implementation')."""

    n_pads: int = 5
    first_pad_x_m: tuple[float, float] = (3.0, 4.5)   # centre of pad 0, uniform range
    gap_m: tuple[float, float] = (3.0, 5.0)           # centre-to-centre spacing, uniform (mean 4 m)
    length_m: tuple[float, float] = (0.8, 1.6)        # pad extent along its own x axis
    width_m: tuple[float, float] = (0.8, 1.6)         # pad extent along its own y axis
    height_m: tuple[float, float] = (0.4, 1.2)        # pad top surface above the floor
    lateral_shift_m: float = 1.0                      # |y| shift of each pad, uniform
    longitudinal_jitter_m: float = 0.3                # extra x shift of each pad, uniform +-
    max_yaw_rad: float = 0.6                          # |yaw| of each pad, uniform
    n_materials: int = 52                             # distinct procedural textures
    texture_px: int = 64                              # texture resolution (square)
    wall_margin_m: float = 5.0                        # room extends this far past the first/last pad
    room_half_width_m: float = 6.0                    # walls at y = +-this
    wall_height_m: float = 6.0
    start_x_m: tuple[float, float] = (-1.0, 1.0)      # start pose, uniform
    start_y_m: tuple[float, float] = (-0.5, 0.5)
    start_altitude_m: tuple[float, float] = (3.0, 4.0)


@dataclass
class VehicleConfig:
    """Quadrotor body: a box with four leg collision shapes under it."""

    mass_kg: float = 1.2
    body_half_extents_m: tuple[float, float, float] = (0.12, 0.12, 0.04)
    leg_offset_m: float = 0.15        # legs at (+-offset, +-offset) in base_link
    leg_length_m: float = 0.12        # leg bottom is this far below base_link
    leg_radius_m: float = 0.012
    lateral_friction: float = 0.9


@dataclass
class ControllerConfig:
    """Velocity-tracking flight controller, like ArduCopter GUIDED velocity control."""

    kp_xy: float = 3.0                 # 1/s, velocity error -> acceleration
    kp_z: float = 4.0
    max_speed_xy_mps: float = 3.0      # commanded speed clamp (WPNAV_SPEED-like)
    max_climb_mps: float = 2.5         # PILOT_SPEED_UP-like
    max_descent_mps: float = 1.5       # PILOT_SPEED_DN-like
    max_accel_xy_mps2: float = 2.5     # WPNAV_ACCEL-like
    max_accel_z_mps2: float = 2.5      # PILOT_ACCEL_Z-like
    attitude_kp: float = 40.0          # 1/s^2, keeps the airframe level
    attitude_kd: float = 10.0          # 1/s
    yaw_rate_max_rad_s: float = 1.57   # used when a yaw target is set (MAVLink vehicle)
    min_thrust_fraction: float = 0.0   # of hover thrust; 0 lets it settle on its legs


@dataclass
class TurbulenceConfig:
    """Gaussian noise on the target velocity, variance growing near the surface below."""

    enabled: bool = True
    sigma_far_mps: float = 0.05        # std far from any surface
    sigma_ground_mps: float = 0.30     # extra std at zero height (ground effect)
    ground_scale_m: float = 0.8        # e-folding height of the ground effect
    correlation_s: float = 0.3         # noise is low-pass filtered with this time constant


@dataclass
class CameraConfig:
    """Downward RGB-D camera (RealSense D435i-like field of view)."""

    width: int = 64
    height: int = 64
    vertical_fov_deg: float = 58.0     # D435i depth: 87 x 58 deg; square images use the vertical FOV
    near_m: float = 0.1
    far_m: float = 20.0
    offset_below_base_m: float = 0.05  # optical centre below base_link origin, on the body z axis
    # 'analytic': per-pixel ray casting of floor, walls and pads in numpy (assist_sim.core.render),
    # pixel-identical to the 'pybullet' path and several times faster; any camera pose.
    # 'pybullet': pybullet's TinyRenderer (the baseline; also what the GUI shows).
    renderer: str = 'analytic'
    # pybullet path only: draw the floor plane analytically (ray-plane intersection + texture
    # lookup) instead of through TinyRenderer, which spends ~85% of a 64x64 frame shading the floor.
    analytic_floor: bool = True
    floor_tile_m: float = 1.5          # floor texture repeat length
    floor_shading: float = 0.935       # TinyRenderer's default lighting of an upward-facing surface


@dataclass
class JudgeConfig:
    """Landing judge thresholds (paper: success = four legs on the goal; crash = below a height)."""

    crash_height_m: float = 0.2        # base_link below this (floor at 0) and not landed -> crash
    crash_speed_mps: float = 3.0       # any contact faster than this -> crash
    crash_tilt_rad: float = 1.0        # airframe tipped over -> crash
    settle_speed_mps: float = 0.05     # landed when slower than this...
    settle_time_s: float = 0.5         # ...for this long while touching something
    arm_height_m: float = 0.3          # the judge starts once base_link has been above floor + this
    max_episode_s: float = 90.0        # then the episode ends as a timeout
    autopilot_confirm_s: float = 3.0   # arducopter plant: how long after a touchdown result its land detector may take


@dataclass
class WorldConfig:
    """Everything the landing world needs."""

    physics_hz: int = 240
    control_hz: int = 20
    gravity_mps2: float = 9.81
    # velocity-mode plant: 'ideal' (the `controller` loop) or 'arducopter' (ArduCopter GUIDED as the
    # bridge flies it: `arducopter` dynamics and land detector, setpoints through the `touchdown` envelope)
    flight_controller: str = 'ideal'
    scene: SceneConfig = field(default_factory=SceneConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    turbulence: TurbulenceConfig = field(default_factory=TurbulenceConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    judge: JudgeConfig = field(default_factory=JudgeConfig)
    arducopter: ArduCopterConfig = field(default_factory=ArduCopterConfig)
    touchdown: TouchdownConfig = field(default_factory=TouchdownConfig)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> WorldConfig:
        """Build from a (possibly partial, nested) mapping; unknown keys raise ValueError."""
        return _from_dict(cls, data or {})

    @classmethod
    def from_yaml(cls, path: str | Path) -> WorldConfig:
        """Load a (possibly partial) YAML file of the same nesting as this dataclass."""
        with open(path, encoding='utf-8') as fh:
            return cls.from_dict(yaml.safe_load(fh) or {})

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (YAML/JSON friendly)."""
        return dataclasses.asdict(self)


def _from_dict(cls, data: Mapping[str, Any]):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields)
    if unknown:
        raise ValueError(f'{cls.__name__}: unknown setting(s) {sorted(unknown)}')
    kwargs = {}
    defaults = cls()
    for name, value in data.items():
        current = getattr(defaults, name)
        if dataclasses.is_dataclass(current):
            kwargs[name] = _from_dict(type(current), value or {})
        elif isinstance(current, tuple):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = type(current)(value) if current is not None else value
    return cls(**kwargs)
