"""The actor as policy_node runs it: ONNX Runtime on a cached export of the actor file, or torch.

Importing torch costs ~2-3 s of CPU at every start of policy_node, more than everything else the node does
before its first step. The `onnxruntime` backend runs an ONNX export of the same network (its GRU and goal
head included) and keeps the export in the user cache (`assist_common.cache`, folder `actors`), keyed by a
hash of the actor file's bytes, torch's version and the export version: a start with a cached export
imports neither torch nor onnx. The cache entry holds the validated metadata and a probe observation with
the outputs torch gave for it at export time; a cached session is used only when it reproduces them (to
PROBE_TOL), and an entry that does not load or agree is exported again and replaced. An export that does not
agree with torch is refused: `auto` then runs torch (with a warning), `onnxruntime` fails.

The `torch` backend is the lab's path (assist_policy.actor: load_actor + run_actor); evaluation and training
run it. The two agree to ~1e-6 in the raw action (test_policy_actor_runtime.py).
"""
from __future__ import annotations

import importlib.util
import io
import json
import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from assist_common.cache import cache_dir, file_key, store_entry, touch
from assist_common.console import package_version
from assist_common.onnx_session import cpu_session

from .actor_meta import learned_goal, validate_actor_meta
from .intent import LearnedGoal
from .observation import IMAGE_SHAPE

_LOG = logging.getLogger(__name__)
BACKENDS = ('auto', 'torch', 'onnxruntime')
CACHE_FOLDER = 'actors'
CACHE_KEEP = 16                 # exported actors kept in the cache, newest first
EXPORT_VERSION = 1              # bump when _export changes what it exports
PROBE_TOL = 1e-4                # raw action and goal-head output, ONNX Runtime against torch on the probe


class ExportDisagrees(Exception):
    """An ONNX export whose outputs differ from torch's on the probe observation."""


class TorchActor:
    """The actor file on torch: `run_actor` of assist_policy.actor (the path evaluation and training fly)."""

    backend = 'torch'

    def __init__(self, path: str | Path, threads: int = 0):
        import torch

        from .actor import load_actor
        if threads > 0:
            torch.set_num_threads(threads)
        self.net, self.meta = load_actor(path)

    def __call__(self, obs: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, LearnedGoal | None]:
        """The raw action for one observation and, with a goal head, the goal estimate (else None)."""
        from .actor import run_actor
        return run_actor(self.net, obs, position)

    def outputs(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Raw actions (N, act_dim) and goal-head outputs (N, GOAL_OUT) or None, for N observations."""
        import torch
        with torch.no_grad():
            x = torch.as_tensor(np.asarray(obs, dtype=np.float32))
            if self.net.goal_head is None:
                return self.net(x).numpy(), None
            action, head = self.net.act_and_goal(x)
            return action.numpy(), head.numpy()


class OnnxActor:
    """The actor file on ONNX Runtime (CPU), from the cached export when there is a usable one."""

    backend = 'onnxruntime'

    def __init__(self, path: str | Path, threads: int = 1):
        self.path, self.threads = Path(path), threads
        self.session, self.meta = self._load()

    def _session(self, model: bytes | Path):
        return cpu_session(model, self.threads)

    def _load(self) -> tuple[Any, dict[str, Any]]:
        """(session, metadata) from the cache when it holds a usable export of this file, else from a new export."""
        folder = cache_dir(CACHE_FOLDER)
        key = export_key(self.path)
        onnx_path = folder / f'{key}.onnx' if folder is not None else None
        if onnx_path is not None and onnx_path.with_suffix('.json').is_file():
            try:
                probe = json.loads(onnx_path.with_suffix('.json').read_text())
                meta = validate_actor_meta(probe['meta'])
                session = self._session(onnx_path)
                _check(self._run(session, np.asarray(probe['obs'], np.float32), meta['goal_head']),
                       np.asarray(probe['action'], np.float32),
                       None if probe['head'] is None else np.asarray(probe['head'], np.float32))
            except Exception as exc:  # noqa: BLE001 - ORT, json and the checks raise many types for a bad entry
                _LOG.warning('cached actor export %s is not usable (%s): exporting it again', onnx_path, exc)
            else:
                touch(onnx_path)
                touch(onnx_path.with_suffix('.json'))
                return session, meta
        torch_actor = TorchActor(self.path)
        data = _export(torch_actor)
        session = self._session(data)
        obs = probe_observation(observation_size(torch_actor.meta))
        action, head = torch_actor.outputs(obs)
        _check(self._run(session, obs, torch_actor.meta['goal_head']), action, head)
        if onnx_path is not None:
            entry = {'meta': torch_actor.meta, 'obs': obs.tolist(), 'action': action.tolist(),
                     'head': None if head is None else head.tolist(), 'source': str(self.path)}
            # the probe last: an entry without it is never read as a hit
            store_entry(onnx_path.parent, key, {'.onnx': data, '.json': json.dumps(entry).encode()}, CACHE_KEEP,
                        'the exported actor')
        return session, torch_actor.meta

    @staticmethod
    def _run(session, obs: np.ndarray, goal_head: bool) -> tuple[np.ndarray, np.ndarray | None]:
        out = session.run(None, {'obs': np.ascontiguousarray(obs, dtype=np.float32)})
        return out[0], (out[1] if goal_head else None)

    def __call__(self, obs: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, LearnedGoal | None]:
        """The raw action for one observation and, with a goal head, the goal estimate (else None)."""
        action, head = self._run(self.session, np.asarray(obs, np.float32)[None], self.meta['goal_head'])
        raw = action[0].astype(float)
        return raw, (None if head is None else learned_goal(head[0], position))


def export_key(path: Path) -> str:
    """A hash of what an export depends on: the actor file's bytes, torch's version, the export version."""
    return file_key(path, str(EXPORT_VERSION), package_version('torch'))


def probe_observation(size: int) -> np.ndarray:
    """A fixed observation (one row of `size` values) to compare an export with torch on."""
    return np.random.default_rng(0).normal(0.0, 1.0, (1, size)).astype(np.float32)


def _check(got: tuple[np.ndarray, np.ndarray | None], action: np.ndarray, head: np.ndarray | None) -> None:
    """ExportDisagrees unless an export's (raw action, goal-head output) equal torch's to PROBE_TOL."""
    for name, g, t in (('raw action', got[0], action), ('goal head', got[1], head)):
        if (g is None) != (t is None) or (t is not None and (g.shape != t.shape or not np.allclose(
                g, t, rtol=0.0, atol=PROBE_TOL, equal_nan=True))):
            raise ExportDisagrees(f'its {name} differs from torch by more than {PROBE_TOL:g} on a probe observation')


def _export(torch_actor: TorchActor) -> bytes:
    """ONNX bytes of the actor: obs (1, observation_size) -> raw action (1, act_dim) [, goal head (1, GOAL_OUT)]."""
    import torch
    from torch import nn

    net = torch_actor.net
    goal = net.goal_head is not None

    class _Outputs(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, obs: torch.Tensor):
            return self.net.act_and_goal(obs) if goal else self.net(obs)

    buf = io.BytesIO()
    with warnings.catch_warnings():
        # torch's TorchScript-based exporter warns that it is legacy; it needs no onnxscript and exports this
        # MLP/GRU exactly (checked against torch on the probe)
        warnings.filterwarnings('ignore', category=DeprecationWarning)
        warnings.filterwarnings('ignore', message='.*legacy TorchScript-based ONNX export.*')
        # the GRU's input checks become constants of the trace: the node runs one observation at a time, the shape
        # the export is traced with (no dynamic batch)
        warnings.filterwarnings('ignore', category=torch.jit.TracerWarning)
        warnings.filterwarnings('ignore', message='.*with a batch_size other than 1.*')
        torch.onnx.export(_Outputs().eval(), (torch.zeros(1, observation_size(torch_actor.meta)),), buf,
                          input_names=['obs'], output_names=['action', 'goal'] if goal else ['action'], dynamo=False)
    return buf.getvalue()


def resolve_backend(backend: str) -> str:
    """'auto' -> onnxruntime when installed (with onnx), else torch; an unknown name -> ValueError."""
    if backend not in BACKENDS:
        raise ValueError(f'unknown actor backend {backend!r} (one of {", ".join(BACKENDS)})')
    have_ort = importlib.util.find_spec('onnxruntime') is not None
    if backend == 'onnxruntime' and not have_ort:
        raise ValueError('actor backend onnxruntime: the onnxruntime package is not installed')
    if backend == 'auto':
        return 'onnxruntime' if have_ort else 'torch'
    return backend


def image_size(meta: dict[str, Any]) -> int:
    """Values of the image at the start of an end-to-end actor's observation (0 for other actors)."""
    return int(np.prod(IMAGE_SHAPE)) if meta['image'] else 0


def observation_size(meta: dict[str, Any]) -> int:
    """Values of one observation the actor reads: the image (end-to-end) followed by the vector."""
    return image_size(meta) + int(meta['vec_dim'])


def load_actor_runtime(path: str | Path, backend: str = 'torch', threads: int = 1) -> TorchActor | OnnxActor:
    """The actor file at `path` on `backend` (auto, torch or onnxruntime); ValueError (one line) for a bad file, or
    for an onnxruntime export that does not agree with torch (auto then runs torch)."""
    chosen = resolve_backend(backend)
    if not Path(path).is_file():
        raise ValueError(f'actor file not found: {path}')
    if chosen == 'torch':
        return TorchActor(path, threads)
    try:
        return OnnxActor(path, threads)
    except ValueError:
        raise
    except Exception as exc:  # noqa: BLE001 - the exporter and ORT raise many types
        if backend == 'onnxruntime':
            raise ValueError(f'actor {path}: cannot run it on onnxruntime ({type(exc).__name__}: {exc})') from None
        _LOG.warning('actor %s: cannot run it on onnxruntime (%s: %s); running it on torch',
                     path, type(exc).__name__, exc)
        return TorchActor(path, threads)

