"""plot_flight: one PNG per landing in a bag, like the paper's trajectory figure.

    plot_flight flights/run1                          # -> flights/run1_plots/run1_landing0.png, ...
    plot_flight runs/eval/bags/latent_beta0.50_seed2024 --out figs/

Each figure: top view (x-y) and side view (x-z) of the flown path with the five pads and the goal
(pads from /sim/scene; without it only the goal from /sim/goal is marked and the landing JSON names the
pads), the stretches where the assistant was active (|a| > blend threshold) highlighted, and pilot (u)
vs assistant (a) vs blended (V) velocity commands over time per axis, with the active stretches shaded.
A bag holds one landing per /sim/landing message (the stretch since the previous one); what follows the
last landing (or a bag without any) gives one more figure, marked unfinished. A landing JSON whose
error_m is not a number (null, text, a list) is drawn with the error marked n/a (warned).
Existing figures are refused, never overwritten (another --out, or move them away); a failed run leaves
no empty output directory behind.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from assist_policy.blending import DEFAULT_THRESHOLD
from . import msgs
from .bagio import BagError, BagReader, check_output, publish_new

log = logging.getLogger(__name__)

PANELS = ('top view (x-y)', 'side view (x-z)', 'forward x (m/s)', 'left y (m/s)', 'up z (m/s)')
TOPICS = ('/odom', '/pilot/cmd_vel', '/assist/agent_cmd', '/cmd_vel', '/sim/goal', '/sim/scene', '/sim/landing')


@dataclass
class Series:
    """Time-stamped vectors (times in seconds from the bag start)."""

    t: list[float] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)

    def add(self, t: float, v) -> None:
        """Append a sample."""
        self.t.append(t)
        self.v.append(np.asarray(v, dtype=float))

    def window(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """(times, values (n, d)) with t0 < t <= t1."""
        t = np.asarray(self.t)
        m = (t > t0) & (t <= t1)
        vals = np.stack(self.v)[m] if self.v else np.zeros((0, 3))
        return t[m], vals


@dataclass
class Flight:
    """Everything plot_flight draws for one landing."""

    t0: float
    t1: float
    odom: tuple[np.ndarray, np.ndarray]
    pilot: tuple[np.ndarray, np.ndarray]
    agent: tuple[np.ndarray, np.ndarray]
    cmd: tuple[np.ndarray, np.ndarray]
    goal: np.ndarray | None
    pads: list[dict]
    goal_index: int | None
    landing: dict | None


def read_flights(bag: str | Path, progress: bool = False) -> list[Flight]:
    """The bag's landings (BagError on a bad bag or one without /odom)."""
    series = {k: Series() for k in ('/odom', '/pilot/cmd_vel', '/assist/agent_cmd', '/cmd_vel')}
    goals: list[tuple[float, np.ndarray]] = []
    scenes: list[tuple[float, list[dict], int | None]] = []
    landings: list[tuple[float, dict]] = []
    with BagReader(bag) as r:
        if '/odom' not in r.topics:
            raise BagError(f'{bag}: no /odom in the bag: nothing to plot')
        used = [t for t in TOPICS if t in r.topics]
        r.check_definitions(used)
        start = r.start_ns
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=sum(r.topics[t].count for t in used), unit='msg', desc='read', file=sys.stderr)
        try:
            for topic, t_ns, raw in r.messages(used):
                t = (t_ns - start) * 1e-9
                msg = r.deserialize(raw, topic)
                try:
                    if topic == '/odom':
                        series[topic].add(t, msgs.odom_arrays(msg)[0])
                    elif topic in series:
                        series[topic].add(t, msgs.twist_linear(msg))
                    elif topic == '/sim/goal':
                        goals.append((t, msgs.point(msg)))
                    elif topic == '/sim/scene':
                        pads, gi = msgs.pads_from_markers(msg)
                        scenes.append((t, pads, gi))
                    elif topic == '/sim/landing':
                        landings.append((t, msgs.landing_json(msg)))
                except ValueError as exc:
                    log.warning('skipping %s at %.2f s: %s', topic, t, exc)
                if bar is not None:
                    bar.update()
        finally:
            if bar is not None:     # before any error line, which must start a line of its own
                bar.close()
        end = (r.end_ns - start) * 1e-9
    bounds = [(-1.0, t) for t, _ in landings[:1]] + [(a[0], b[0]) for a, b in zip(landings, landings[1:])]
    if not landings:
        bounds = [(-1.0, end)]
    elif len(series['/odom'].window(landings[-1][0], end)[0]) > 20:    # an unfinished flight after the last landing
        bounds.append((landings[-1][0], end))
    flights = []
    for i, (t0, t1) in enumerate(bounds):
        landing = landings[i][1] if i < len(landings) else None

        def last(items, t1=t1):
            before = [x for x in items if x[0] <= t1]
            return before[-1] if before else (items[0] if items else None)
        g = last(goals)
        sc = last(scenes)
        goal_index = sc[2] if sc and sc[2] is not None else (landing or {}).get('goal_index')
        flights.append(Flight(t0, t1, series['/odom'].window(t0, t1), series['/pilot/cmd_vel'].window(t0, t1),
                              series['/assist/agent_cmd'].window(t0, t1), series['/cmd_vel'].window(t0, t1),
                              g[1] if g else None, sc[1] if sc else [], goal_index, landing))
    return flights


def _active_spans(t: np.ndarray, a: np.ndarray, threshold: float) -> list[tuple[float, float]]:
    """Time spans where |a| > threshold."""
    if len(t) == 0:
        return []
    on = np.linalg.norm(a, axis=1) > threshold
    spans, begin = [], None
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.05
    for ti, o in zip(t, on):
        if o and begin is None:
            begin = ti
        elif not o and begin is not None:
            spans.append((begin, ti))
            begin = None
    if begin is not None:
        spans.append((begin, t[-1] + dt))
    return spans


def _pad_outline(pad: dict) -> np.ndarray:
    cx, cy, _ = pad['centre']
    lx, ly = pad['size'][0] / 2, pad['size'][1] / 2
    c, s = np.cos(pad['yaw']), np.sin(pad['yaw'])
    corners = np.array([[lx, ly], [-lx, ly], [-lx, -ly], [lx, -ly], [lx, ly]])
    return corners @ np.array([[c, s], [-s, c]]) + [cx, cy]


def plot_flight(f: Flight, path: Path, title: str, threshold: float = DEFAULT_THRESHOLD):
    """Draw one landing into a PNG at `path` (written to a temporary name, then renamed); returns the figure."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(12, 7.5))
    gs = fig.add_gridspec(2, 3, height_ratios=(1.2, 1))
    top, side = fig.add_subplot(gs[0, :2]), fig.add_subplot(gs[0, 2])
    axes = [fig.add_subplot(gs[1, i]) for i in range(3)]
    to, po = f.odom
    ta, av = f.agent
    spans = _active_spans(ta, av, threshold)
    active_pos = np.zeros(len(to), bool)
    for b, e in spans:
        active_pos |= (to >= b) & (to < e)
    for i, pad in enumerate(f.pads):
        goal = i == f.goal_index
        o = _pad_outline(pad)
        top.fill(o[:, 0], o[:, 1], color='tab:green' if goal else '0.7', alpha=0.5 if goal else 0.6, lw=0)
        top.text(pad['centre'][0], pad['centre'][1], str(i), ha='center', va='center', fontsize=8)
        half_x = np.abs(o[:4, 0] - pad['centre'][0]).max()
        side.fill_between([pad['centre'][0] - half_x, pad['centre'][0] + half_x], 0, pad['size'][2],
                          color='tab:green' if goal else '0.7', alpha=0.5 if goal else 0.6, lw=0)
    if len(po):
        for ax, j in ((top, 1), (side, 2)):
            ax.plot(po[:, 0], po[:, j], color='tab:blue', lw=1.2, label='path')
            act = np.where(active_pos, po[:, j], np.nan)
            ax.plot(po[:, 0], act, color='tab:orange', lw=3, alpha=0.8, label='assistant active')
            ax.plot(po[0, 0], po[0, j], 'o', color='tab:blue', ms=5, label='start')
            ax.plot(po[-1, 0], po[-1, j], 'x', color='k', ms=7, label='end')
    if f.goal is not None:
        top.plot(f.goal[0], f.goal[1], '*', color='tab:red', ms=14, label='goal')
        side.plot(f.goal[0], f.goal[2], '*', color='tab:red', ms=14)
    top.set_title(PANELS[0])
    top.set_xlabel('x (m)')
    top.set_ylabel('y (m)')
    top.set_aspect('equal', adjustable='datalim')
    top.legend(fontsize=7, loc='best')
    side.set_title(PANELS[1])
    side.set_xlabel('x (m)')
    side.set_ylabel('z (m)')
    side.set_ylim(bottom=0)
    for k, ax in enumerate(axes):
        for (t, v), name, style in ((f.pilot, 'pilot u', dict(color='tab:blue')),
                                    (f.agent, 'assistant a', dict(color='tab:orange', alpha=0.8)),
                                    (f.cmd, 'blended V', dict(color='k', ls='--'))):
            if len(t):
                ax.plot(t - (f.odom[0][0] if len(f.odom[0]) else 0), v[:, k], lw=1, label=name, **style)
        for b, e in spans:
            off = f.odom[0][0] if len(f.odom[0]) else 0
            ax.axvspan(b - off, e - off, color='tab:orange', alpha=0.12, lw=0)
        ax.set_title(PANELS[2 + k])
        ax.set_xlabel('time (s)')
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    tmp = path.with_name(f'.{path.stem}.partial-{os.getpid()}.png')
    try:
        fig.savefig(tmp, dpi=100)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise BagError(f'{path}: cannot write ({exc.strerror})') from None
    finally:
        plt.close(fig)
    publish_new(tmp, path)
    return fig


def landing_error(landing: dict) -> float | None:
    """The landing's error_m when it is a finite number, else None (warned)."""
    v = landing.get('error_m')
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    log.warning('landing %s: error_m is %r, not a number; drawn as n/a', landing.get('episode', '?'), v)
    return None


def describe(f: Flight, name: str, k: int) -> str:
    """Figure title: bag, landing number and outcome."""
    if f.landing is None:
        return f'{name} flight {k}: no /sim/landing recorded (unfinished)'
    L = f.landing
    pads = '' if f.pads else '  [pads not recorded (/sim/scene): goal from /sim/goal only]'
    err = landing_error(L)
    return (f"{name} landing {k}: goal pad {L.get('goal_index')}, landed on {L.get('landed_index')}, "
            f"error {'n/a' if err is None else f'{err:.2f} m'}, "
            f"{'success' if L.get('success') else ('crash' if L.get('crash') else 'miss')}, "
            f"{'assisted' if L.get('assisted') else 'unassisted'}{pads}")


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    p = argparse.ArgumentParser(prog='plot_flight', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('bag', help='bag directory (or .mcap/.db3 file)')
    p.add_argument('--out', default='', help='directory for the PNGs (default: <bag>_plots)')
    p.add_argument('--threshold', type=float, default=DEFAULT_THRESHOLD,
                   help='|a| (m/s) above which the assistant counts as active (the blending threshold)')
    a = p.parse_args(argv)
    bag = Path(a.bag.rstrip('/'))
    name = bag.stem if bag.suffix in ('.mcap', '.db3') else bag.name
    out = Path(a.out) if a.out else bag.with_name(name + '_plots')
    created: list[Path] = []            # directories this run made (removed again when it fails empty)
    written: list[str] = []
    try:
        if out.is_dir():
            pattern = re.compile(re.escape(name) + r'_landing\d+\.png')
            old = sorted(p.name for p in out.iterdir() if pattern.fullmatch(p.name))
            if old:
                raise BagError(f'{out / old[0]}: exists already; not overwriting ({len(old)} figures of this bag '
                               f'in {out}: choose another --out)')
        else:
            check_output(out)
        flights = read_flights(bag, progress=True)
        for d in reversed([out, *out.parents]):
            if not d.exists():
                d.mkdir()
                created.append(d)
        for k, f in enumerate(flights):
            path = out / f'{name}_landing{k}.png'
            plot_flight(f, path, describe(f, name, k), a.threshold)
            written.append(str(path))
    except (BagError, OSError) as exc:
        for d in reversed(created):     # what was written stays; an empty directory of this run goes
            try:
                d.rmdir()
            except OSError:
                break
        print(f'error: {exc}', file=sys.stderr)
        if written:
            print(f'kept: {", ".join(written)}', file=sys.stderr)
        return 1
    print('written: ' + ', '.join(written))
    return 0


if __name__ == '__main__':
    sys.exit(main())
