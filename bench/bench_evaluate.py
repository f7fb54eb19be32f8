"""Evaluate section of `make bench`: landings per second against `evaluate --workers`, the CPU one landing costs,
and what the paper's protocol (four conditions x 840 landings) takes here and on a 64-core Ray-sized cluster."""
from __future__ import annotations

import resource
import tempfile
import time
from pathlib import Path

# unassisted, latent (renders and encodes every frame) and the oracle, three pilot skills: a mix of cheap and
# expensive landings like the paper's
PLAN = dict(conditions=('unassisted', 'latent', 'oracle'), betas=(0.0, 0.5, 1.0), landings=4, plot=False)
PAPER_LANDINGS = 4 * 840
CLUSTER_CORES = 64


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _ray_rows(tmp: Path, n: int, local_rate: float) -> list[dict]:
    """The same plan as Ray tasks on a local Ray instance (started before the clock: a cluster is up already)."""
    from assist_lab.cluster import connect_ray
    from assist_lab.evaluate import EvalArgs, evaluate
    try:
        ray = connect_ray('auto')
    except ValueError as exc:
        return [{'name': 'evaluate --ray auto', 'value': f'not measured: {exc}', 'unit': ''}]
    try:
        t0 = time.perf_counter()
        evaluate(EvalArgs(out=str(tmp / 'ray'), ray='auto', **PLAN))
        ray_rate = n / (time.perf_counter() - t0)
    finally:
        ray.shutdown()
    return [{'name': f'evaluate --ray auto (local instance, {n} landings)', 'value': ray_rate, 'unit': 'landings/s'},
            {'name': 'Ray over 2 local worker processes', 'value': ray_rate / local_rate, 'unit': 'x',
             'target': '>= 0.85'}]


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    import torch

    from assist_lab.cluster import cpu_cores
    from assist_lab.evaluate import EvalArgs, evaluate

    torch.set_num_threads(1)
    cores = cpu_cores()
    rows, rate = [], {}
    n = len(PLAN['conditions']) * len(PLAN['betas']) * PLAN['landings']
    per_landing_cpu = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for workers in sorted({1, min(2, cores)}):
            c0, t0 = _cpu_s(), time.perf_counter()
            evaluate(EvalArgs(out=str(Path(tmp) / f'w{workers}'), workers=workers, **PLAN))
            wall, cpu = time.perf_counter() - t0, _cpu_s() - c0
            rate[workers] = n / wall
            if workers == 1:
                per_landing_cpu = cpu / n
            rows.append({'name': f'evaluate --workers {workers}: {n} landings ({", ".join(PLAN["conditions"])})',
                         'value': rate[workers], 'unit': 'landings/s',
                         'target': '>= 1.6x of 1 worker' if workers == 2 else ''})
        if 2 in rate:
            rows.append({'name': 'evaluate speed-up, 2 workers over 1', 'value': rate[2] / rate[1], 'unit': 'x',
                         'target': '>= 1.6'})
            rows += _ray_rows(Path(tmp), n, rate[2])
    rows.append({'name': 'CPU per landing (one process; includes start-up)', 'value': per_landing_cpu, 'unit': 's'})
    best = max(rate.values())
    rows.append({'name': f'paper protocol ({PAPER_LANDINGS} landings) on this machine, best workers',
                 'value': PAPER_LANDINGS / best / 60, 'unit': 'min'})
    rows.append({'name': f'paper protocol projected on {CLUSTER_CORES} cores (CPU per landing / cores)',
                 'value': PAPER_LANDINGS * per_landing_cpu / CLUSTER_CORES / 60, 'unit': 'min'})
    return rows
