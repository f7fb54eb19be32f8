"""ArduPilot SITL JSON backend: lock-step rate against a SITL stand-in, and what a tilting camera does
to the CM-VAE's pad estimate.

1. Throughput: sim_node's JsonSimRunner (400 Hz physics, camera 20 Hz, rng_1) serves a SITL
   stand-in (assist_sim.testing_sitl) over UDP loopback, lock-step, as fast as the stand-in can
   send. Reported: frames/s and x-real-time on the wall clock, and per CPU-second of the backend
   thread alone (one core: must be >= 1x to keep up with SITL at --speedup 1).
2. Tilt: in ardupilot_json mode the camera is rigidly mounted, so frames tilt with the airframe
   (velocity mode keeps it level). Frames rendered above the pads at roll/pitch tilts of 0..20 deg
   go through the shipped CM-VAE (clean depth): error of the pad estimate in the (tilted) optical
   frame against the label, and the horizontal world error when a consumer reads that estimate
   as if the camera were level (what the latent/policy implicitly does), and the same after
   encoder_node's `level_camera` re-renders the frame as a level camera (assist_perception.level).
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from assist_sim.core.config import WorldConfig
from assist_sim.core.runner import RunnerConfig
from assist_sim.core.world import LandingWorld
from assist_sim.json_backend import JsonBackendConfig, JsonSimRunner
from assist_sim.testing_sitl import SitlStandIn

SIM_SECONDS = 20.0      # per rate measured
RATE = 400
TILTS_DEG = (0, 5, 10, 15, 20)
TILT_SCENES = 30


def throughput(rate: int = RATE) -> list[dict]:
    """Lock-step frames/s of the JSON backend (runner thread) against the stand-in (main thread)."""
    world = LandingWorld(WorldConfig(), seed=0)
    runner = JsonSimRunner(world, RunnerConfig(airborne_start=False, camera_rate_hz=20.0), JsonBackendConfig(port=0))
    runner.reset(3)
    c = runner.model.cfg
    hover = c.pwm_for_command(c.command_for_thrust(world.cfg.vehicle.mass_kg * 9.81 / 4))
    stop = threading.Event()
    cpu = {}
    frames_rendered = []

    def serve():
        t0 = time.thread_time()
        while not stop.is_set():
            out = runner.step()
            if out.frame is not None:
                frames_rendered.append(1)
        cpu['backend'] = time.thread_time() - t0
    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    sitl = SitlStandIn(port=runner.server.address[1], frame_rate=rate)
    n = int(SIM_SECONDS * rate)
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(n):
        # landed and disarmed for the first quarter, then a slow climb (contacts, then free flight)
        pwm = [1000] * 4 if i < n // 4 else [hover + 15] * 4
        if sitl.exchange(pwm, timeout=2.0) is None:
            raise RuntimeError(f'no reply to frame {i}')
    wall, proc_cpu = time.perf_counter() - t0, time.process_time() - c0
    stop.set()
    thread.join(timeout=5)
    sitl.close()
    runner.close()
    world.close()
    sim = n / rate
    if rate != RATE:      # 800: the shipped .parm's SIM_RATE_HZ; 1200: SITL's default at ArduPilot 90700977c553
        return [{'name': f'x real time per CPU-second of the backend thread at {rate} Hz',
                 'value': sim / cpu['backend'], 'unit': 'x', 'target': '>= 1x'}]
    return [
        {'name': f'lock-step frames/s vs stand-in, wall ({rate} Hz physics, camera 20 Hz)', 'value': n / wall,
         'unit': 'frames/s'},
        {'name': 'x real time, wall clock (stand-in + backend on this machine)', 'value': sim / wall, 'unit': 'x',
         'target': '>= 1x (SITL --speedup 1)'},
        {'name': 'x real time per CPU-second of the backend thread (one core)', 'value': sim / cpu['backend'],
         'unit': 'x', 'target': '>= 1x'},
        {'name': 'x real time per CPU-second, whole process (backend + stand-in)', 'value': sim / proc_cpu,
         'unit': 'x'},
        {'name': 'camera frames rendered per sim second', 'value': len(frames_rendered) / sim, 'unit': 'frames/s',
         'target': '20'},
    ]


def _tilt_matrix(tilt: float, azimuth: float) -> np.ndarray:
    """Rotation by `tilt` about the horizontal axis at `azimuth` (body FLU -> ENU, yaw 0)."""
    axis = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(tilt) * k + (1 - math.cos(tilt)) * k @ k


def tilt_effect() -> list[dict]:
    """CM-VAE pad estimate error vs camera tilt (median over scenes and random tilt directions)."""
    from scipy.spatial.transform import Rotation

    from assist_lab.cmvae_dataset import pad_label
    from assist_perception.encoder_core import LatentEncoder
    from assist_perception.level import level_frame, level_rotation

    enc = LatentEncoder(threads=1)
    world = LandingWorld(WorldConfig(), seed=0)
    rng = np.random.default_rng(0)
    err_opt = {t: [] for t in TILTS_DEG}
    err_level = {t: [] for t in TILTS_DEG}
    vid = world._vehicle
    err_levelled = {t: [] for t in TILTS_DEG}
    for s in range(TILT_SCENES):
        world.reset(1000 + s, airborne=True)
        pad = world.scene.pads[int(rng.integers(len(world.scene.pads)))]
        base = pad.top_center + np.array([*rng.uniform(-0.6, 0.6, 2), rng.uniform(1.2, 2.5)])
        azimuth = rng.uniform(-math.pi, math.pi)
        heading = rng.uniform(-math.pi, math.pi)
        for t in TILTS_DEG:
            r = _tilt_matrix(math.radians(t), azimuth) @ Rotation.from_euler('z', heading).as_matrix()
            q = Rotation.from_matrix(r).as_quat()
            world._bc.resetBasePositionAndOrientation(vid, base.tolist(), q.tolist())
            frame = world.render()                       # the vehicle's rigidly mounted camera
            cam, r_wo = world.camera_pose()
            lab = pad_label(frame.depth, frame.K, cam, r_wo, world.scene.pads, 12, 0.02)
            if not lab.visible:
                continue
            pred = enc.encode(frame.rgb, frame.depth).pad_xyz.astype(float)
            err_opt[t].append(float(np.linalg.norm(pred - lab.xyz)))
            target = world.scene.pads[lab.index].top_center
            r_level = level_rotation(q)
            r_wo_level = r_wo @ r_level.T                # same optical centre and heading, level
            seen_level = cam + r_wo_level @ pred          # read as if the camera were level
            err_level[t].append(float(np.linalg.norm(seen_level[:2] - target[:2])))
            rgb2, depth2 = level_frame(frame.rgb, frame.depth, frame.K, r_level)    # encoder_node level_camera
            seen2 = cam + r_wo_level @ enc.encode(rgb2, depth2).pad_xyz.astype(float)
            err_levelled[t].append(float(np.linalg.norm(seen2[:2] - target[:2])))
    world.close()
    rows = []
    for t in TILTS_DEG:
        rows.append({'name': f'tilt {t:2d} deg: pad estimate error, tilted optical frame (median, n={len(err_opt[t])})',
                     'value': float(np.median(err_opt[t])), 'unit': 'm'})
        rows.append({'name': f'tilt {t:2d} deg: horizontal error if read as a level camera (median)',
                     'value': float(np.median(err_level[t])), 'unit': 'm'})
        rows.append({'name': f'tilt {t:2d} deg: horizontal error after levelling (encoder_node level_camera)',
                     'value': float(np.median(err_levelled[t])), 'unit': 'm'})
    return rows


def run() -> list[dict]:
    """Both measurements."""
    return throughput() + throughput(800) + throughput(1200) + tilt_effect()


if __name__ == '__main__':
    for row in run():
        print(f"{row['name']:<90} {row['value']:.3f} {row.get('unit', '')}")
