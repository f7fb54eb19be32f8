"""ONNX Runtime sessions as the vehicle's networks run them (the CM-VAE encoder, the actor): CPU, one observation at a
time beside other nodes on a small machine."""
from __future__ import annotations

from pathlib import Path
from typing import Any


def cpu_session(model: bytes | str | Path, threads: int = 1) -> Any:
    """An onnxruntime InferenceSession on the CPU for `model` (ONNX bytes or a file): `threads` intra-op threads
    (0 = ORT's default, one per core), sequential execution, every graph optimisation, idle threads sleeping instead
    of spinning (a 20 Hz path must not burn a core), errors only in ORT's own log."""
    import onnxruntime as ort   # imported here: only the onnxruntime backends need it

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(0, int(threads))
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry('session.intra_op.allow_spinning', '0')
    opts.log_severity_level = 3
    return ort.InferenceSession(model if isinstance(model, bytes) else str(model), opts,
                                providers=['CPUExecutionProvider'])
