"""fit_guided: fit the ArduCopter GUIDED model (assist_sim.core.arducopter) to logs of real ArduCopter SITL.

The logs are the CSV fixtures `sitl_identify` writes (one command sequence per file: time, the velocity
setpoint sent, the vehicle's true velocity and position, ENU). The model is run as a point mass on each
file's setpoints from its first velocity (`arducopter.simulate`) and its velocity compared with the log.
Files whose name starts with `random` (the pilot-like random sequences) are never fitted: they only test it.

    fit_guided --fixtures ros2_ws/src/assist_sim/test/fixtures/guided --out runs/guided_fit

writes `fit.yaml` (a world_config `arducopter:` section with the fitted values) and `report.csv`
(velocity RMSE per file, before and after), and logs the same.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import logging
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from assist_common.atomic import write_text_atomic
from assist_common.settings import SettingsError, check_settings, exit_error, setting

from .core.arducopter import ArduCopterConfig, simulate

log = logging.getLogger(__name__)

COLUMNS = ('t_s', 'cmd_x', 'cmd_y', 'cmd_z', 'vel_x', 'vel_y', 'vel_z')
HELD_OUT_PREFIX = 'random'
# what is fitted by default: the lags and gains that are not ArduCopter parameters with known defaults
DEFAULT_FIT = ('setpoint_delay_s', 'attitude_tc_s', 'throttle_tc_s', 'vel_xy_p', 'vel_z_p')


@dataclass
class Fixture:
    """One logged command sequence (ENU, m/s) and its header lines."""

    name: str
    header: dict[str, str]
    t: np.ndarray        # (N,) s from the sequence start
    cmd: np.ndarray      # (N, 3) the setpoint last sent at t
    vel: np.ndarray      # (N, 3) the vehicle's velocity at t
    command_hz: float = 0.0  # setpoints were sent on this grid from t = 0 (0: at every sample)

    def sends(self) -> tuple[np.ndarray, np.ndarray]:
        """(send times, setpoints): the setpoint stream as sent (on the command grid, from the logged values)."""
        if self.command_hz <= 0.0:
            return self.t, self.cmd
        k = np.floor(self.t * self.command_hz + 1e-6).astype(int)
        first = np.concatenate([[True], k[1:] != k[:-1]])       # the first log sample after each send
        return k[first] / self.command_hz, self.cmd[first]

    @property
    def held_out(self) -> bool:
        """Never used to fit, only to test."""
        return self.name.startswith(HELD_OUT_PREFIX)


def load_fixture(path: str | Path) -> Fixture:
    """Read one fixture CSV (`# key: value` header lines, then the columns; the `setpoints` line names the
    command rate, e.g. '... 20 Hz'); ValueError naming the file if malformed."""
    path = Path(path)
    header: dict[str, str] = {}
    rows: list[str] = []
    with open(path, encoding='utf-8') as fh:
        for line in fh:
            if line.startswith('#'):
                key, _, value = line[1:].partition(':')
                header[key.strip()] = value.strip()
            elif line.strip():
                rows.append(line)
    reader = csv.DictReader(rows)
    missing = set(COLUMNS) - set(reader.fieldnames or ())
    if missing:
        raise ValueError(f'{path}: missing columns {sorted(missing)}')
    try:
        data = np.array([[float(r[c]) for c in COLUMNS] for r in reader], dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{path}: bad value: {exc}') from exc
    if len(data) < 10 or not np.all(np.isfinite(data)) or np.any(np.diff(data[:, 0]) <= 0):
        raise ValueError(f'{path}: needs >= 10 rows of finite values with increasing time')
    rate = re.search(r'([0-9.]+) Hz', header.get('setpoints', ''))
    return Fixture(path.stem, header, data[:, 0] - data[0, 0], data[:, 1:4], data[:, 4:7],
                   float(rate.group(1)) if rate else 0.0)


def load_fixtures(folder: str | Path) -> list[Fixture]:
    """Every command-sequence CSV of a folder (sorted by name); ValueError if there is none."""
    files = sorted(p for p in Path(folder).glob('*.csv') if not p.name.startswith('touchdown'))
    if not files:
        raise ValueError(f'{folder}: no fixture CSV files')
    return [load_fixture(p) for p in files]


def response(cfg: ArduCopterConfig, fx: Fixture) -> np.ndarray:
    """The model's velocity (N, 3) on a fixture's setpoints, from its first logged velocity."""
    send_t, send_sp = fx.sends()
    v, _ = simulate(cfg, fx.t, send_sp, velocity0=fx.vel[0], command_times=send_t)
    return v


def rmse(cfg: ArduCopterConfig, fx: Fixture) -> float:
    """Velocity RMSE (m/s, over the three axes) of the model against a fixture."""
    return float(np.sqrt(np.mean((response(cfg, fx) - fx.vel) ** 2)))


def step_metrics(t: np.ndarray, v: np.ndarray, t_step: float, v0: float, v1: float) -> dict[str, float]:
    """10-90 % rise time (s) and overshoot (fraction of the step) of one axis' response to a step at t_step."""
    after = t >= t_step
    tt, vv = t[after], v[after]
    span = v1 - v0
    frac = (vv - v0) / span
    i10 = int(np.argmax(frac >= 0.1)) if np.any(frac >= 0.1) else len(tt) - 1
    i90 = int(np.argmax(frac >= 0.9)) if np.any(frac >= 0.9) else len(tt) - 1
    return {'rise_s': float(tt[i90] - tt[i10]), 'overshoot': float(max(0.0, np.max(frac) - 1.0))}


def fit(base: ArduCopterConfig, fixtures: list[Fixture], names: tuple[str, ...]) -> ArduCopterConfig:
    """Least-squares fit of the fields `names` (within their ranges) to the velocity of `fixtures`."""
    from scipy.optimize import least_squares
    rules = {f.name: f.metadata['settings_rule'] for f in dataclasses.fields(ArduCopterConfig)}
    x0 = np.array([getattr(base, n) for n in names], dtype=float)
    lo = np.array([rules[n].ge for n in names], dtype=float)
    hi = np.array([rules[n].le for n in names], dtype=float)

    def residuals(x: np.ndarray) -> np.ndarray:
        cfg = dataclasses.replace(base, **dict(zip(names, map(float, x))))
        return np.concatenate([(response(cfg, fx) - fx.vel).ravel() for fx in fixtures])

    sol = least_squares(residuals, np.clip(x0, lo, hi), bounds=(lo, hi), x_scale=np.maximum(np.abs(x0), 0.05),
                        diff_step=1e-3, max_nfev=200)
    return dataclasses.replace(base, **dict(zip(names, (round(float(v), 4) for v in sol.x))))


@dataclass
class FitArgs:
    """Command-line arguments of fit_guided."""

    fixtures: str = setting('ros2_ws/src/assist_sim/test/fixtures/guided', nonempty=True)
    out: str = setting('runs/guided_fit', nonempty=True)
    params: tuple[str, ...] = setting(DEFAULT_FIT, min_len=1,
                                      choices=tuple(f.name for f in dataclasses.fields(ArduCopterConfig)
                                                    if f.type in ('float', float)))


def main(argv: list[str] | None = None) -> int:
    """fit_guided entry point (module docstring)."""
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    ap = argparse.ArgumentParser(prog='fit_guided', description=__doc__.split('\n\n')[0])
    ap.add_argument('--fixtures', default=FitArgs.fixtures, help='folder of sitl_identify CSV files')
    ap.add_argument('--out', default=FitArgs.out, help='output folder (fit.yaml, report.csv)')
    ap.add_argument('--params', nargs='+', default=list(DEFAULT_FIT), help='ArduCopterConfig fields to fit')
    ns = ap.parse_args(argv)
    args = FitArgs(ns.fixtures, ns.out, tuple(ns.params))
    try:
        check_settings(args)
        fixtures = load_fixtures(args.fixtures)
    except (SettingsError, ValueError, OSError) as exc:
        exit_error('fit_guided', exc, 2)
    train = [f for f in fixtures if not f.held_out]
    if not train:
        exit_error('fit_guided', f'{args.fixtures}: every fixture is held out ({HELD_OUT_PREFIX}*)', 2)
    base = ArduCopterConfig()
    fitted = fit(base, train, args.params)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [{'fixture': f.name, 'held_out': f.held_out, 'rmse_default': round(rmse(base, f), 4),
             'rmse_fitted': round(rmse(fitted, f), 4)} for f in fixtures]
    lines = ['fixture,held_out,rmse_default,rmse_fitted'] + [
        f"{r['fixture']},{r['held_out']},{r['rmse_default']},{r['rmse_fitted']}" for r in rows]
    write_text_atomic(out / 'report.csv', '\n'.join(lines) + '\n')
    section = {'arducopter': {n: getattr(fitted, n) for n in args.params}}
    write_text_atomic(out / 'fit.yaml', yaml.safe_dump(section, sort_keys=False))
    for r in rows:
        log.info('%-28s %s rmse %.4f -> %.4f m/s', r['fixture'], 'held out' if r['held_out'] else 'fitted  ',
                 r['rmse_default'], r['rmse_fitted'])
    log.info('fitted: %s (written to %s)', section['arducopter'], out / 'fit.yaml')
    return 0


if __name__ == '__main__':
    sys.exit(main())
