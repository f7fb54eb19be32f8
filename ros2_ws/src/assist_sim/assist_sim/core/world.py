"""The landing world: pybullet scene, quadrotor with legs, velocity flight controller,
ground-effect turbulence, downward RGB-D camera and the landing judge. No rclpy here."""
from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from assist_common.frames import R_BODY_FROM_OPTICAL, yaw_rotation
from assist_common.settings import check_named
from assist_common.touchdown import TouchdownEnvelope

from .arducopter import FLIGHT_CONTROLLERS, GuidedVelocityModel
from .config import WorldConfig
from .quiet import quiet_output
from .render import SceneRenderer
from .scene import PadSpec, SceneSpec, generate_scene
from .textures import make_texture, texture_path

with quiet_output():                 # pybullet prints its build time on import
    import pybullet as p
    from pybullet_utils import bullet_client

_LOG = logging.getLogger(__name__)
N_LEGS = 4
RENDERERS = ('analytic', 'pybullet')
WALL_TILE_M = 1.5                      # wall texture repeat length


@dataclass(frozen=True)
class VehicleState:
    """Kinematic state of base_link in odom (ENU), velocities in odom except angular (body)."""

    time: float
    position: np.ndarray
    quaternion: np.ndarray          # x, y, z, w (odom -> base_link)
    velocity: np.ndarray            # m/s, odom frame
    angular_velocity: np.ndarray    # rad/s, body frame
    yaw: float
    height_above_surface: float     # base_link above whatever is straight below it


@dataclass(frozen=True)
class CameraFrame:
    """One downward RGB-D frame with intrinsics (optical frame: z out of the lens)."""

    rgb: np.ndarray                 # HxWx3 uint8
    depth: np.ndarray               # HxW float32, metres along the optical axis
    K: np.ndarray                   # 3x3 intrinsics
    time: float = 0.0

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return int(self.rgb.shape[0])


@dataclass
class LandingResult:
    """Outcome of one landing, serialised as the contract's /sim/landing JSON."""

    episode: int
    goal_index: int
    landed_index: int | None
    nearest_index: int
    error_m: float
    nearest_error_m: float
    success: bool
    crash: bool
    duration_s: float
    assisted: bool = False
    outcome: str = 'success'        # success | wrong_pad | edge | crash | timeout
    reason: str = ''
    # flight_controller arducopter: whether its land detector declared the landing within the
    # judge's autopilot_confirm_s after the result (None on the ideal plant or for no touchdown)
    autopilot_landed: bool | None = None

    def to_dict(self) -> dict:
        """Plain dict with JSON-friendly values."""
        return asdict(self)

    def to_json(self) -> str:
        """One JSON object (the /sim/landing message payload)."""
        return json.dumps(self.to_dict())


def turbulence_sigma(height_m: float, cfg) -> float:
    """Std of the target-velocity noise at a leg clearance `height_m` above the surface below."""
    h = max(0.0, float(height_m))
    return cfg.sigma_far_mps + cfg.sigma_ground_mps * math.exp(-h / cfg.ground_scale_m)


def camera_intrinsics(width: int, height: int, vertical_fov_deg: float) -> np.ndarray:
    """Pinhole intrinsics of the OpenGL projection used by the renderer (square pixels)."""
    fy = (height / 2.0) / math.tan(math.radians(vertical_fov_deg) / 2.0)
    return np.array([[fy, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def linearize_depth(zbuf: np.ndarray, near: float, far: float) -> np.ndarray:
    """OpenGL z-buffer in [0,1] -> metric depth along the optical axis."""
    return (far * near / (far - (far - near) * zbuf)).astype(np.float32)


class BulletClient(bullet_client.BulletClient):
    """pybullet_utils' BulletClient whose destructor tolerates a construction interrupted before `connect`
    returned (a Ctrl-C while sim_node starts): the original then prints an AttributeError traceback at exit."""

    def __del__(self):
        if '_client' in self.__dict__:
            super().__del__()


class LandingWorld:
    """One pybullet world (own DIRECT client) that training, tests and sim_node all drive."""

    def __init__(self, cfg: WorldConfig | None = None, seed: int = 0, gui: bool = False):
        self.cfg = cfg or WorldConfig()
        if self.cfg.physics_hz < 240:
            raise ValueError('physics_hz must be >= 240')
        if self.cfg.physics_hz % self.cfg.control_hz:
            raise ValueError('physics_hz must be a multiple of control_hz')
        if self.cfg.camera.renderer not in RENDERERS:
            raise ValueError(f'camera.renderer must be one of {RENDERERS}, got {self.cfg.camera.renderer!r}')
        if self.cfg.flight_controller not in FLIGHT_CONTROLLERS:
            raise ValueError(f'flight_controller must be one of {FLIGHT_CONTROLLERS}, '
                             f'got {self.cfg.flight_controller!r}')
        # ArduCopter's GUIDED response and the touchdown envelope the bridge applies (None: the ideal loop)
        self._fc: GuidedVelocityModel | None = None
        self._touchdown: TouchdownEnvelope | None = None
        if self.cfg.flight_controller == 'arducopter':
            self._fc, self._touchdown = self._arducopter(self.cfg.arducopter)
        self._gui = bool(gui)
        with quiet_output(stderr=not gui):  # ... and `argv[0]=` on every connect (GUI: keep X errors)
            self._bc = BulletClient(p.GUI if gui else p.DIRECT)
        self._cid = self._bc._client
        self._tick_dt = 1.0 / self.cfg.physics_hz
        self._bc.setGravity(0, 0, -self.cfg.gravity_mps2)
        self._bc.setPhysicsEngineParameter(fixedTimeStep=1.0 / self.cfg.physics_hz, numSubSteps=0,
                                           deterministicOverlappingPairs=1)
        self._seed_seq = np.random.SeedSequence(seed)
        self._textures: dict[int, int] = {}
        self._scene_bodies: list[int] = []
        self._pad_ids: list[int] = []
        self._floor_id = -1
        self._scene_renderer: SceneRenderer | None = None
        # the GUI shows pybullet's own rendering, so the camera uses it as well there
        self._analytic = self.cfg.camera.renderer == 'analytic' and not self._gui
        self.scene: SceneSpec | None = None
        self.goal_index = 0
        self.episode = -1
        self.time = 0.0
        # seconds since the episode started, summed from zero: never `time - start`, whose rounding depends on
        # how long the world has run (a landing's duration_s then depended on the landings flown before it)
        self.episode_time = 0.0
        self._rng = np.random.default_rng(seed)
        self._noise = np.zeros(3)
        self._cmd_world = np.zeros(3)
        self._yaw_target = 0.0
        self._armed = True
        self._judge_active = False
        self._settle_timer = 0.0
        self._was_touching = False
        self.result: LandingResult | None = None
        self._K = camera_intrinsics(self.cfg.camera.width, self.cfg.camera.height,
                                    self.cfg.camera.vertical_fov_deg)
        # TinyRenderer clears the z-buffer to 1.0 (float32); anything at the far plane is "empty"
        self._zbuf_empty = np.float32(1.0) - np.float32(1e-7)
        uu, vv = np.meshgrid(np.arange(self.cfg.camera.width), np.arange(self.cfg.camera.height))
        self._rays = np.stack([(uu - self._K[0, 2]) / self._K[0, 0], (vv - self._K[1, 2]) / self._K[1, 1],
                               np.ones_like(uu, dtype=float)], axis=-1)   # optical, z = 1
        self._proj = self._bc.computeProjectionMatrixFOV(
            self.cfg.camera.vertical_fov_deg, self.cfg.camera.width / self.cfg.camera.height,
            self.cfg.camera.near_m, self.cfg.camera.far_m)
        self._vehicle = self._build_vehicle()
        self._mass = self.cfg.vehicle.mass_kg
        self._inertia = np.array(self._bc.getDynamicsInfo(self._vehicle, -1)[2])

    # ------------------------------------------------------------------ building
    def _texture(self, material: int) -> int:
        if material not in self._textures:
            self._textures[material] = self._bc.loadTexture(
                str(texture_path(material, self.cfg.scene.texture_px)))
        return self._textures[material]

    def _textured_quad(self, corners: np.ndarray, normal, tile_m: float) -> int:
        """Visual shape of a flat quad (4 corners CCW seen from the normal) with tiled UVs."""
        e1 = np.linalg.norm(corners[1] - corners[0]) / tile_m
        e2 = np.linalg.norm(corners[3] - corners[0]) / tile_m
        return self._bc.createVisualShape(
            p.GEOM_MESH, vertices=corners.tolist(), indices=[0, 1, 2, 0, 2, 3],
            uvs=[[0, 0], [e1, 0], [e1, e2], [0, e2]], normals=[list(normal)] * 4)

    def _build_vehicle(self) -> int:
        v = self.cfg.vehicle
        bc = self._bc
        body_col = bc.createCollisionShape(p.GEOM_BOX, halfExtents=v.body_half_extents_m)
        body_vis = bc.createVisualShape(p.GEOM_BOX, halfExtents=v.body_half_extents_m,
                                        rgbaColor=[0.15, 0.15, 0.15, 1])
        leg_len = v.leg_length_m - v.body_half_extents_m[2]
        leg_col = bc.createCollisionShape(p.GEOM_CAPSULE, radius=v.leg_radius_m,
                                          height=max(leg_len - 2 * v.leg_radius_m, 1e-3))
        leg_vis = bc.createVisualShape(p.GEOM_CAPSULE, radius=v.leg_radius_m,
                                       length=max(leg_len - 2 * v.leg_radius_m, 1e-3),
                                       rgbaColor=[0.3, 0.3, 0.3, 1])
        o = v.leg_offset_m
        zc = -v.body_half_extents_m[2] - leg_len / 2
        leg_pos = [[o, o, zc], [o, -o, zc], [-o, o, zc], [-o, -o, zc]]
        leg_mass = 0.02
        vid = bc.createMultiBody(
            baseMass=v.mass_kg - N_LEGS * leg_mass, baseCollisionShapeIndex=body_col,
            baseVisualShapeIndex=body_vis, basePosition=[0, 0, 3],
            linkMasses=[leg_mass] * N_LEGS, linkCollisionShapeIndices=[leg_col] * N_LEGS,
            linkVisualShapeIndices=[leg_vis] * N_LEGS, linkPositions=leg_pos,
            linkOrientations=[[0, 0, 0, 1]] * N_LEGS, linkInertialFramePositions=[[0, 0, 0]] * N_LEGS,
            linkInertialFrameOrientations=[[0, 0, 0, 1]] * N_LEGS, linkParentIndices=[0] * N_LEGS,
            linkJointTypes=[p.JOINT_FIXED] * N_LEGS, linkJointAxis=[[0, 0, 1]] * N_LEGS)
        for link in range(-1, N_LEGS):
            bc.changeDynamics(vid, link, lateralFriction=v.lateral_friction, linearDamping=0.0,
                              angularDamping=0.0)
        return vid

    def _clear_scene(self) -> None:
        for b in self._scene_bodies:
            self._bc.removeBody(b)
        self._scene_bodies, self._pad_ids = [], []

    def _build_scene(self, scene: SceneSpec) -> None:
        bc = self._bc
        self._clear_scene()
        self._scene_renderer = None        # built on the first analytic frame of this scene
        (x0, y0), (x1, y1) = scene.room_min, scene.room_max
        cam = self.cfg.camera
        self._floor_texture = make_texture(scene.floor_material, self.cfg.scene.texture_px)
        self._floor_bounds = (x0, y0, x1, y1)
        if cam.analytic_floor and not self._gui:
            self._floor_id = bc.createMultiBody(0, bc.createCollisionShape(p.GEOM_PLANE), -1)
            # a body without a visual is drawn from its collision shape: make it invisible instead
            bc.changeVisualShape(self._floor_id, -1, rgbaColor=[0, 0, 0, 0])
        else:
            floor_vis = self._textured_quad(
                np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]]), (0, 0, 1), tile_m=cam.floor_tile_m)
            self._floor_id = bc.createMultiBody(0, bc.createCollisionShape(p.GEOM_PLANE), floor_vis)
            bc.changeVisualShape(self._floor_id, -1, textureUniqueId=self._texture(scene.floor_material),
                                 rgbaColor=[1, 1, 1, 1])
        bc.changeDynamics(self._floor_id, -1, lateralFriction=0.9)
        self._scene_bodies.append(self._floor_id)
        h = scene.wall_height
        walls = [  # inward-facing quads
            ([[x0, y1, 0], [x1, y1, 0], [x1, y1, h], [x0, y1, h]], (0, -1, 0)),
            ([[x1, y0, 0], [x0, y0, 0], [x0, y0, h], [x1, y0, h]], (0, 1, 0)),
            ([[x0, y0, 0], [x0, y1, 0], [x0, y1, h], [x0, y0, h]], (1, 0, 0)),
            ([[x1, y1, 0], [x1, y0, 0], [x1, y0, h], [x1, y1, h]], (-1, 0, 0)),
        ]
        for corners, normal in walls:
            corners = np.array(corners, dtype=float)
            centre = corners.mean(axis=0)
            vis = self._textured_quad(corners - centre, normal, tile_m=WALL_TILE_M)
            half = np.abs(corners - centre).max(axis=0)
            half = np.maximum(half, 0.05)
            col = bc.createCollisionShape(p.GEOM_BOX, halfExtents=half.tolist())
            wid = bc.createMultiBody(0, col, vis, basePosition=centre.tolist())
            bc.changeVisualShape(wid, -1, textureUniqueId=self._texture(scene.wall_material),
                                 rgbaColor=[1, 1, 1, 1])
            self._scene_bodies.append(wid)
        for pad in scene.pads:
            half = [pad.length / 2, pad.width / 2, pad.height / 2]
            col = bc.createCollisionShape(p.GEOM_BOX, halfExtents=half)
            vis = bc.createVisualShape(p.GEOM_BOX, halfExtents=half)
            pid = bc.createMultiBody(0, col, vis, basePosition=[pad.center[0], pad.center[1], pad.height / 2],
                                     baseOrientation=bc.getQuaternionFromEuler([0, 0, pad.yaw]))
            bc.changeVisualShape(pid, -1, textureUniqueId=self._texture(pad.material), rgbaColor=[1, 1, 1, 1])
            bc.changeDynamics(pid, -1, lateralFriction=0.9)
            self._pad_ids.append(pid)
            self._scene_bodies.append(pid)

    # ------------------------------------------------------------------ episodes
    def reset(self, seed: int | None = None, *, scene: SceneSpec | None = None,
              goal_index: int | None = None, start_position=None, airborne: bool = True) -> VehicleState:
        """Start a new episode: new scene (from `seed` or the world's sequence), goal pad, start pose."""
        if seed is None:
            seed = int(self._seed_seq.spawn(1)[0].generate_state(1)[0] & 0x7FFFFFFF)
        self._rng = np.random.default_rng(seed)
        self.scene = scene if scene is not None else generate_scene(self._rng, self.cfg.scene)
        self._build_scene(self.scene)
        n = len(self.scene.pads)
        self.goal_index = int(self._rng.integers(n)) if goal_index is None else int(goal_index)
        if not 0 <= self.goal_index < n:
            raise ValueError(f'goal_index {self.goal_index} out of range 0..{n - 1}')
        start = np.array(self.scene.start_position if start_position is None else start_position, dtype=float)
        if not airborne:
            start[2] = self.cfg.vehicle.leg_length_m + 0.002
        self._bc.resetBasePositionAndOrientation(self._vehicle, start.tolist(), [0, 0, 0, 1])
        self._bc.resetBaseVelocity(self._vehicle, [0, 0, 0], [0, 0, 0])
        self.episode += 1
        self.episode_time = 0.0
        self._noise = np.zeros(3)
        self._cmd_world = np.zeros(3)
        self._yaw_target = 0.0
        self._armed = airborne
        self._judge_active = airborne and start[2] > self.cfg.judge.arm_height_m + self.cfg.judge.crash_height_m
        self._settle_timer = 0.0
        self._was_touching = False
        self.result = None
        if self._fc is not None:
            self._fc.reset(start, np.zeros(3), landed=not airborne)
            self._touchdown.reset()
        return self.state

    @property
    def done(self) -> bool:
        """True once the current episode has a result."""
        return self.result is not None

    def change_goal(self, index: int) -> None:
        """The goal pad becomes `index` from now on (a pilot who changes their mind): the landing is judged on it."""
        index = int(index)
        if not 0 <= index < len(self.scene.pads):
            raise ValueError(f'goal_index {index} out of range 0..{len(self.scene.pads) - 1}')
        self.goal_index = index

    @property
    def goal_position(self) -> np.ndarray:
        """Top-surface centre of the goal pad (odom ENU)."""
        return self.scene.pads[self.goal_index].top_center

    @property
    def pad_top_centers(self) -> np.ndarray:
        """(n_pads, 3) top-surface centres."""
        return self.scene.pad_top_centers

    @property
    def turbulence_velocity(self) -> np.ndarray:
        """Turbulence currently added to the target velocity (odom ENU, m/s)."""
        return self._noise.copy()

    # ------------------------------------------------------------------ arming / yaw
    @property
    def armed(self) -> bool:
        """Motors produce thrust."""
        return self._armed

    def set_armed(self, armed: bool) -> None:
        """Arm (thrust on) or disarm (no thrust: the vehicle falls or rests)."""
        self._armed = bool(armed)

    @property
    def flight_controller(self):
        """The ArduCopter plant's model (`core.arducopter.GuidedVelocityModel`), None on the ideal plant."""
        return self._fc

    @property
    def touchdown(self) -> TouchdownEnvelope | None:
        """The touchdown envelope the ArduCopter plant's setpoints pass through (None on the ideal plant)."""
        return self._touchdown

    def _arducopter(self, cfg) -> tuple[GuidedVelocityModel, TouchdownEnvelope]:
        """The ArduCopter plant's model and envelope (ValueError naming a setting out of range)."""
        model = GuidedVelocityModel(cfg, self.cfg.gravity_mps2)
        check_named(self.cfg.touchdown, 'touchdown')
        return model, TouchdownEnvelope(self.cfg.touchdown)

    def set_flight_controller(self, name: str, arducopter=None) -> None:
        """Fly the rest of this episode on another plant ('ideal' or 'arducopter' with these `ArduCopterConfig`
        settings, default the world config's), starting from the current state (training draws it per landing)."""
        if name not in FLIGHT_CONTROLLERS:
            raise ValueError(f'flight_controller must be one of {FLIGHT_CONTROLLERS}, got {name!r}')
        if name == 'ideal':
            self._fc = self._touchdown = None
            return
        self._fc, self._touchdown = self._arducopter(arducopter if arducopter is not None else self.cfg.arducopter)
        st = self.state
        self._fc.reset(st.position, st.velocity, landed=not self._armed)

    def takeoff(self) -> None:
        """ArduCopter plant: leave its landed state (a take-off command); nothing on the ideal plant."""
        if self._fc is not None and self._fc.landed:
            st = self.state
            self._fc.takeoff(st.position, st.velocity)
            self._touchdown.reset()

    def set_yaw_target(self, yaw: float) -> None:
        """Heading the attitude controller turns to (rate-limited); 0 by default."""
        if not math.isfinite(yaw):
            raise ValueError('yaw target must be finite')
        self._yaw_target = float(yaw)

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> VehicleState:
        """Current state of base_link."""
        pos, orn = self._bc.getBasePositionAndOrientation(self._vehicle)
        lin, ang = self._bc.getBaseVelocity(self._vehicle)
        rot = np.array(self._bc.getMatrixFromQuaternion(orn)).reshape(3, 3)
        yaw = math.atan2(rot[1, 0], rot[0, 0])
        return VehicleState(time=self.time, position=np.array(pos), quaternion=np.array(orn),
                            velocity=np.array(lin), angular_velocity=rot.T @ np.array(ang), yaw=yaw,
                            height_above_surface=self._height_above_surface(np.array(pos)))

    def _height_above_surface(self, pos: np.ndarray) -> float:
        hit = self._bc.rayTest(pos.tolist(), [pos[0], pos[1], pos[2] - 50.0])[0]
        # the ray starts inside the vehicle body, so skip the vehicle itself
        if hit[0] == self._vehicle:
            hits = self._bc.rayTestBatch([pos.tolist()], [[pos[0], pos[1], pos[2] - 50.0]],
                                         reportHitNumber=2)
            hit = hits[0] if hits and hits[0][0] != self._vehicle else hit
        if hit[0] < 0:
            return float(pos[2])
        return float(pos[2] - hit[3][2])

    @property
    def landed(self) -> bool:
        """Resting on something: a leg touches a surface and the vehicle is nearly still."""
        st = self.state
        return self._legs_touching() and float(np.linalg.norm(st.velocity)) < 0.2

    def _contacts(self) -> list:
        return self._bc.getContactPoints(bodyA=self._vehicle)

    def _legs_touching(self) -> bool:
        return any(c[3] >= 0 for c in self._contacts())

    # ------------------------------------------------------------------ stepping
    def step(self, cmd: np.ndarray, dt: float | None = None, frame: str = 'body') -> VehicleState:
        """Fly velocity target `cmd` (body FLU by default, or 'world' ENU) for dt seconds."""
        cmd = np.asarray(cmd, dtype=float).reshape(-1)
        if cmd.shape != (3,) or not np.all(np.isfinite(cmd)):
            raise ValueError(f'velocity command must be 3 finite numbers, got {cmd!r}')
        dt = 1.0 / self.cfg.control_hz if dt is None else float(dt)
        n = max(1, int(round(dt * self.cfg.physics_hz)))
        pos, orn = p.getBasePositionAndOrientation(self._vehicle, physicsClientId=self._cid)
        if frame == 'body':
            r = p.getMatrixFromQuaternion(orn)
            cmd = yaw_rotation(math.atan2(r[3], r[0])) @ cmd
        elif frame != 'world':
            raise ValueError(f"frame must be 'body' or 'world', got {frame!r}")
        self._cmd_world = self._clamp_command(cmd)
        if self._fc is not None:
            self._command_autopilot(np.asarray(pos))
        self._update_turbulence(np.asarray(pos), n / self.cfg.physics_hz)
        had_result = self.result is not None
        for _ in range(n):
            self._physics_tick()
        if self._fc is not None and not had_result and self.result is not None:
            self._confirm_autopilot_landing()
        return self.state

    def _command_autopilot(self, pos: np.ndarray) -> None:
        """ArduCopter plant: the setpoint through the touchdown envelope (the downward range as a
        rangefinder reads it); a climb setpoint while landed stands for the take-off command."""
        fc = self._fc
        if fc.landed and self._cmd_world[2] > self.cfg.touchdown.abort_climb_mps:
            self.takeoff()
        self._cmd_world = self._touchdown.apply(self._cmd_world, self._height_above_surface(pos), self.episode_time)
        fc.command(self._cmd_world)

    def _confirm_autopilot_landing(self) -> None:
        """After a touchdown result, fly on (same setpoint, no camera) until ArduCopter's land detector
        declares the landing or `judge.autopilot_confirm_s` passes; record which in the result."""
        res = self.result
        if res.outcome == 'timeout' or res.reason in ('tipped over', 'fell below the crash height') \
                or res.reason.startswith('impact'):
            return
        steps = int(round(self.cfg.judge.autopilot_confirm_s * self.cfg.physics_hz))
        for _ in range(steps):
            if self._fc.landed:
                break
            self._physics_tick()
        res.autopilot_landed = bool(self._fc.landed)

    def _clamp_command(self, v: np.ndarray) -> np.ndarray:
        c = self.cfg.controller
        out = v.copy()
        sp = float(np.hypot(out[0], out[1]))
        if sp > c.max_speed_xy_mps:
            out[:2] *= c.max_speed_xy_mps / sp
        out[2] = float(np.clip(out[2], -c.max_descent_mps, c.max_climb_mps))
        return out

    def _update_turbulence(self, pos: np.ndarray, dt: float) -> None:
        t = self.cfg.turbulence
        if not t.enabled or not self._armed:
            self._noise[:] = 0.0
            return
        sigma = turbulence_sigma(self._height_above_surface(pos) - self.cfg.vehicle.leg_length_m, t)
        a = math.exp(-dt / t.correlation_s)
        self._noise = a * self._noise + math.sqrt(1 - a * a) * sigma * self._rng.standard_normal(3)

    def _physics_tick(self) -> None:
        # Hot path (physics_hz): raw pybullet calls with the client id, plain float maths.
        cid, vid, c, g = self._cid, self._vehicle, self.cfg.controller, self.cfg.gravity_mps2
        pos, orn = p.getBasePositionAndOrientation(vid, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(vid, physicsClientId=cid)
        tilt_target = (0.0, 0.0, 1.0)
        if self._armed and self._fc is not None:
            # ArduCopter plant: its model gives the acceleration; the airframe leans to produce it
            m = self._mass
            a = self._fc.tick(pos, lin, self._tick_dt, touching=self._was_touching, disturbance=self._noise)
            fx, fy, fz = m * a[0], m * a[1], max(m * (a[2] + g), 0.0)
            tilt_target = self._fc.thrust_direction()
            p.applyExternalForce(vid, -1, (fx, fy, fz), pos, p.WORLD_FRAME, physicsClientId=cid)
        elif self._armed:
            tx, ty, tz = self._cmd_world + self._noise
            m = self._mass
            if self._was_touching and self._cmd_world[2] <= 0.0:
                # ArduCopter's land detector: on the ground and not climbing -> spool down.
                fx, fy, fz = 0.0, 0.0, c.min_thrust_fraction * m * g
            else:
                ax, ay = c.kp_xy * (tx - lin[0]), c.kp_xy * (ty - lin[1])
                a_xy = math.hypot(ax, ay)
                if a_xy > c.max_accel_xy_mps2:
                    ax, ay = ax * c.max_accel_xy_mps2 / a_xy, ay * c.max_accel_xy_mps2 / a_xy
                az = min(max(c.kp_z * (tz - lin[2]), -c.max_accel_z_mps2), c.max_accel_z_mps2)
                fx, fy, fz = m * ax, m * ay, max(m * (az + g), 0.0)
            p.applyExternalForce(vid, -1, (fx, fy, fz), pos, p.WORLD_FRAME, physicsClientId=cid)
        if self._armed:
            # attitude hold: the thrust direction (level on the ideal plant), commanded heading (rate-limited yaw)
            r = p.getMatrixFromQuaternion(orn)
            yaw = math.atan2(r[3], r[0])
            yaw_err = (self._yaw_target - yaw + math.pi) % (2 * math.pi) - math.pi
            yaw_rate_cmd = min(max(2.0 * yaw_err, -c.yaw_rate_max_rad_s), c.yaw_rate_max_rad_s)
            # tilt error = body z axis x target z axis (x, y components)
            t0, t1, t2 = tilt_target
            ex, ey = r[5] * t2 - r[8] * t1, r[8] * t0 - r[2] * t2
            kp, kd = c.attitude_kp, c.attitude_kd
            alpha_w = np.array([kp * ex - kd * ang[0], kp * ey - kd * ang[1], kd * (yaw_rate_cmd - ang[2])])
            rot = np.array(r).reshape(3, 3)
            torque = rot @ (self._inertia * (rot.T @ alpha_w))
            p.applyExternalTorque(vid, -1, torque.tolist(), p.WORLD_FRAME, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        self.time += self._tick_dt
        self.episode_time += self._tick_dt
        self._judge(lin)

    # ------------------------------------------------------------------ judge
    def _judge(self, v_before: np.ndarray) -> None:
        j = self.cfg.judge
        contacts = p.getContactPoints(bodyA=self._vehicle, physicsClientId=self._cid)
        touching = len(contacts) > 0
        new_contact = touching and not self._was_touching
        self._was_touching = touching
        if self.result is not None:
            return
        pos, orn = p.getBasePositionAndOrientation(self._vehicle, physicsClientId=self._cid)
        if not self._judge_active:
            if pos[2] > j.arm_height_m + j.crash_height_m:
                self._judge_active = True
            return
        impact = math.sqrt(v_before[0] ** 2 + v_before[1] ** 2 + v_before[2] ** 2)
        if new_contact and impact > j.crash_speed_mps:
            self._finish('crash', None, f'impact at {impact:.2f} m/s')
            return
        r22 = p.getMatrixFromQuaternion(orn)[8]
        if math.acos(min(max(r22, -1.0), 1.0)) > j.crash_tilt_rad:
            self._finish('crash', None, 'tipped over')
            return
        legs_on: dict[int, set[int]] = {}
        for c in contacts:
            if c[3] >= 0:
                legs_on.setdefault(c[2], set()).add(c[3])
        pad_legs = {self._pad_ids.index(b): legs for b, legs in legs_on.items() if b in self._pad_ids}
        full_pad = next((k for k, legs in pad_legs.items() if len(legs) == N_LEGS), None)
        if pos[2] < j.crash_height_m and full_pad is None:
            self._finish('crash', None, 'fell below the crash height')
            return
        if touching and math.sqrt(sum(x * x for x in p.getBaseVelocity(
                self._vehicle, physicsClientId=self._cid)[0])) < j.settle_speed_mps:
            self._settle_timer += 1.0 / self.cfg.physics_hz
        else:
            self._settle_timer = 0.0
        if self._settle_timer >= j.settle_time_s:
            if full_pad is not None:
                self._finish('success' if full_pad == self.goal_index else 'wrong_pad', full_pad, 'landed')
            elif pad_legs:
                most = max(pad_legs, key=lambda k: len(pad_legs[k]))
                self._finish('edge', most, f'{len(pad_legs[most])} of {N_LEGS} legs on pad {most}')
            elif self._floor_id in legs_on:
                self._finish('crash', None, 'landed on the floor')
            else:
                self._finish('edge', None, 'resting on something that is not a pad')
            return
        if self.episode_time >= j.max_episode_s:
            self._finish('timeout', None, f'no landing within {j.max_episode_s:.0f} s')

    def _finish(self, outcome: str, landed_index: int | None, reason: str) -> None:
        pos = np.array(self._bc.getBasePositionAndOrientation(self._vehicle)[0])
        centres = self.scene.pad_top_centers[:, :2]
        dists = np.linalg.norm(centres - pos[:2], axis=1)
        nearest = int(np.argmin(dists))
        self.result = LandingResult(
            episode=self.episode, goal_index=self.goal_index, landed_index=landed_index,
            nearest_index=nearest, error_m=float(dists[self.goal_index]),
            nearest_error_m=float(dists[nearest]), success=outcome == 'success',
            crash=outcome == 'crash', duration_s=float(self.episode_time),
            outcome=outcome, reason=reason)
        _LOG.debug('episode %d finished: %s (%s)', self.episode, outcome, reason)

    # ------------------------------------------------------------------ camera
    def camera_pose(self, position=None, yaw: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Optical centre (odom) and R_world_from_optical, for the vehicle or a given base pose."""
        if position is None:
            pos, orn = self._bc.getBasePositionAndOrientation(self._vehicle)
            r_wb = np.array(self._bc.getMatrixFromQuaternion(orn)).reshape(3, 3)
            base = np.array(pos)
        else:
            base = np.asarray(position, dtype=float)
            r_wb = yaw_rotation(0.0 if yaw is None else yaw)
        cam = base + r_wb @ np.array([0.0, 0.0, -self.cfg.camera.offset_below_base_m])
        return cam, r_wb @ R_BODY_FROM_OPTICAL

    def render(self) -> CameraFrame:
        """RGB-D frame from the vehicle's downward camera."""
        cam, r_wo = self.camera_pose()
        return self.render_pose(cam, r_wo)

    def render_from(self, position, yaw: float = 0.0) -> CameraFrame:
        """RGB-D frame as if base_link were level at `position` with heading `yaw`."""
        cam, r_wo = self.camera_pose(position, yaw)
        if self._analytic:                 # the airframe is never in its own camera's view
            return self.render_pose(cam, r_wo)
        saved = self._bc.getBasePositionAndOrientation(self._vehicle)
        vel = self._bc.getBaseVelocity(self._vehicle)
        # move the airframe to the camera pose so it is behind the lens, as in flight
        self._bc.resetBasePositionAndOrientation(
            self._vehicle, np.asarray(position, dtype=float).tolist(),
            self._bc.getQuaternionFromEuler([0, 0, yaw]))
        try:
            return self.render_pose(cam, r_wo)
        finally:
            self._bc.resetBasePositionAndOrientation(self._vehicle, *saved)
            self._bc.resetBaseVelocity(self._vehicle, *vel)

    def render_pose(self, cam: np.ndarray, r_wo: np.ndarray) -> CameraFrame:
        """RGB-D frame from optical centre `cam` (odom) with rotation `r_wo` (odom <- optical), any
        attitude; drawn by the configured renderer (camera.renderer: analytic or pybullet)."""
        if self._analytic:
            if self._scene_renderer is None:
                c = self.cfg.camera
                self._scene_renderer = SceneRenderer(
                    self.scene, width=c.width, height=c.height, vertical_fov_deg=c.vertical_fov_deg,
                    near_m=c.near_m, far_m=c.far_m, floor_tile_m=c.floor_tile_m,
                    floor_shading=c.floor_shading, wall_tile_m=WALL_TILE_M, texture_px=self.cfg.scene.texture_px)
            rgb, depth = self._scene_renderer.render(cam, r_wo)
            return CameraFrame(rgb=rgb, depth=depth, K=self._K.copy(), time=self.time)
        return self._render_pybullet(np.asarray(cam, dtype=float), np.asarray(r_wo, dtype=float))

    def _render_pybullet(self, cam: np.ndarray, r_wo: np.ndarray) -> CameraFrame:
        c = self.cfg.camera
        forward = r_wo[:, 2]
        up = -r_wo[:, 1]                      # image up = -optical y
        view = self._bc.computeViewMatrix(cam.tolist(), (cam + forward).tolist(), up.tolist())
        _, _, rgba, zbuf, _ = self._bc.getCameraImage(
            c.width, c.height, view, self._proj, renderer=p.ER_TINY_RENDERER,
            flags=p.ER_NO_SEGMENTATION_MASK, shadow=0)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(c.height, c.width, 4)[:, :, :3].copy()
        zbuf = np.asarray(zbuf, dtype=np.float32).reshape(c.height, c.width)
        depth = linearize_depth(zbuf, c.near_m, c.far_m)
        if c.analytic_floor and not self._gui:
            self._draw_floor(cam, r_wo, zbuf >= self._zbuf_empty, rgb, depth)
        return CameraFrame(rgb=rgb, depth=depth, K=self._K.copy(), time=self.time)

    def _draw_floor(self, cam: np.ndarray, r_wo: np.ndarray, empty: np.ndarray, rgb: np.ndarray,
                    depth: np.ndarray) -> None:
        """Fill pixels the rasteriser left empty with the textured floor plane z = 0."""
        if not empty.any():
            return
        c = self.cfg.camera
        rays = self._rays[empty]                        # (n, 3) optical, z = 1
        dz = rays @ r_wo[2]                             # world z of each ray direction
        hit = dz < -1e-9
        t = np.full(rays.shape[0], np.inf)
        t[hit] = -cam[2] / dz[hit]                      # optical z-depth of the floor hit
        ok = hit & (t <= c.far_m)
        pts = cam[:2] + t[ok, None] * (rays[ok] @ r_wo[:2].T)
        px = self._floor_texture.shape[0]
        # same texel mapping as the textured quad: u along +x, v along +y from the room corner
        x0, y0 = self._floor_bounds[0], self._floor_bounds[1]
        tu = np.floor((pts[:, 0] - x0) / c.floor_tile_m * px).astype(np.int64) % px
        tv = np.floor((pts[:, 1] - y0) / c.floor_tile_m * px).astype(np.int64) % px
        d = np.full(rays.shape[0], c.far_m, dtype=np.float32)
        d[ok] = t[ok]
        col = np.zeros((rays.shape[0], 3), dtype=np.uint8)
        col[ok] = (self._floor_texture[px - 1 - tv, tu] * c.floor_shading).astype(np.uint8)
        depth[empty] = d
        rgb[empty] = col

    @property
    def camera_intrinsics(self) -> np.ndarray:
        """3x3 K of the configured camera."""
        return self._K.copy()

    # ------------------------------------------------------------------ misc
    def close(self) -> None:
        """Disconnect the pybullet client."""
        if self._bc is not None:
            try:
                self._bc.disconnect()
            finally:
                self._bc = None


__all__ = ['LandingWorld', 'VehicleState', 'CameraFrame', 'LandingResult', 'PadSpec', 'SceneSpec',
           'camera_intrinsics', 'linearize_depth', 'turbulence_sigma']
