"""ONNX Runtime backend of the network: the same weights, a faster CPU forward.

:class:`OrtNetwork` wraps a loaded :class:`SemFeatNet` (from the safetensors weights, BatchNorm
already folded): on the first frame of each network input size it exports the network with
``torch.onnx.export`` into memory and opens an ONNX Runtime session on those bytes. No ONNX file
is written or read, so the safetensors weights stay the only artefact and nothing loaded from
disk is executed.

Why: PyTorch's eager CPU convolutions depend heavily on the CPU's vector units. On an AVX2-only
CPU (no AVX-512, no BF16) the fused channels-last forward at 640x512 took 62.5 ms against 47 ms
on an AVX-512 machine; on the AVX2 CPU ONNX Runtime runs the same graph in 37.8 ms
(1.65x; ``extract()`` at 1920x1536: 66 against 120 ms), with outputs equal to about 1e-5
(``python -m semfeat_ros.model.benchmark``).

Sessions are kept per input size in a least-recently-used cache of :data:`MAX_SESSIONS` sizes
(each holds about 30 MB at 640x512); a session is built without holding the lock that the
inference of the other, ready sizes takes, so a new size never stalls them.

The intra-op threads do not spin by default: the nodes share the CPU with each other (see the
``OMP_WAIT_POLICY`` note in :mod:`semfeat_ros.model`).
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
import importlib.util
import io
import threading
from typing import Any
import warnings

import torch
from torch import nn

from semfeat_ros.model.errors import ModelConfigError

OUTPUTS = ('heatmap', 'descriptors', 'segmentation_logits')
"""Outputs of the exported graph (the extractor's subset of :meth:`SemFeatNet.forward`)."""

OPSET = 17
"""ONNX opset of the export (pixel_shuffle, bilinear resize and softmax are all native)."""

MAX_SESSIONS = 3
"""Input sizes whose sessions are kept (least recently used evicted first)."""


def onnxruntime_available() -> bool:
    """True when both ``onnxruntime`` (the runtime) and ``onnx`` (the exporter's) import."""
    return all(importlib.util.find_spec(m) is not None for m in ('onnxruntime', 'onnx'))


GraphTransform = Callable[[bytes, int, int], bytes]
"""``(graph, height, width) -> graph``: a rewrite of the exported fp32 graph of one input size
before its session opens (e.g. :func:`semfeat_ros.model.quantize.quantize_int8`)."""


def open_session(graph: bytes, num_threads: int, spin: bool = False) -> Any:
    """An ONNX Runtime CPU session on the serialized ``graph``: ``num_threads`` intra-op
    threads, one inter-op thread, all graph optimisations, idle threads spinning only when
    ``spin``."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(num_threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # errors only
    opts.add_session_config_entry('session.intra_op.allow_spinning', '1' if spin else '0')
    return ort.InferenceSession(graph, opts, providers=['CPUExecutionProvider'])


class _Outputs(nn.Module):
    """SemFeatNet with a tuple of the outputs in :data:`OUTPUTS` (ONNX needs fixed outputs)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        pred = self.model(image)
        return tuple(pred[k] for k in OUTPUTS)


class OrtNetwork:
    """Callable like the network: ``(1, 3, H, W)`` float tensor -> dict of output tensors.

    Args:
        model: the network in eval mode (BatchNorm folded or not: the graph is exported as is).
        num_threads: ONNX Runtime intra-op threads (CPU cores).
        spin: let idle intra-op threads spin-wait (faster alone, slower beside other busy
            processes on few cores).
        max_sessions: input sizes whose sessions are kept (LRU).
        transform: applied to each exported graph before its session opens (None: the fp32
            graph as exported).
    Raises:
        ModelConfigError: onnxruntime or onnx is not installed.
    """

    def __init__(self, model: nn.Module, num_threads: int, spin: bool = False,
                 max_sessions: int = MAX_SESSIONS,
                 transform: GraphTransform | None = None) -> None:
        if not onnxruntime_available():
            raise ModelConfigError("backend 'onnxruntime' needs the onnxruntime and onnx "
                                   "packages (pip install -r requirements.txt); or set backend "
                                   "'torch'")
        if model.training:
            raise ModelConfigError('OrtNetwork: the model must be in eval mode')
        self.model = _Outputs(model).eval()
        self.num_threads = int(num_threads)
        self.spin = bool(spin)
        if max_sessions < 1:
            raise ModelConfigError(f'OrtNetwork: max_sessions must be >= 1, got {max_sessions}')
        self.max_sessions = int(max_sessions)
        self.transform = transform
        self.evicted = 0  # sessions dropped from the cache
        self._sessions: OrderedDict[tuple[int, int], Any] = OrderedDict()  # LRU order
        self._building: dict[tuple[int, int], threading.Event] = {}
        self._lock = threading.Lock()  # guards the two dicts; never held while building
        self._export_lock = threading.Lock()  # one export at a time (tracing is not reentrant)

    def export(self, height: int, width: int) -> bytes:
        """The ONNX graph (serialized protobuf) for a ``(1, 3, height, width)`` input."""
        x = torch.zeros(1, int(self.model.model.conf['in_channels']), height, width)
        buf = io.BytesIO()
        with warnings.catch_warnings():  # tracer notes on the (static) shape checks
            warnings.simplefilter('ignore')
            torch.onnx.export(self.model, (x,), buf, dynamo=False, opset_version=OPSET,
                              input_names=['image'], output_names=list(OUTPUTS))
        return buf.getvalue()

    def session(self, height: int, width: int) -> Any:
        """The ONNX Runtime session of one input size (exported and opened on first use, once
        also when several threads ask for it; other sizes stay usable meanwhile)."""
        key = (int(height), int(width))
        while True:
            with self._lock:
                sess = self._sessions.get(key)
                if sess is not None:
                    self._sessions.move_to_end(key)
                    return sess
                event = self._building.get(key)
                owner = event is None
                if owner:
                    event = self._building[key] = threading.Event()
            if owner:
                break
            event.wait()  # built by another thread; on its failure this thread tries
        try:
            sess = self._open(*key)
            with self._lock:
                self._sessions[key] = sess
                while len(self._sessions) > self.max_sessions:
                    self._sessions.popitem(last=False)
                    self.evicted += 1
            return sess
        finally:
            with self._lock:
                del self._building[key]
            event.set()

    def _open(self, height: int, width: int) -> Any:
        with self._export_lock:
            graph = self.export(height, width)
            if self.transform is not None:
                graph = self.transform(graph, height, width)
        return open_session(graph, self.num_threads, self.spin)

    def __call__(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """Forward of a normalised image.

        Args:
            image: (1, C_in, H, W) float32, as for :meth:`SemFeatNet.forward`.
        Returns:
            ``heatmap`` (1, H, W), ``descriptors`` (1, D, H/8, W/8) and ``segmentation_logits``
            (1, C, H/4, W/4), float32 tensors sharing memory with ONNX Runtime's outputs.
        """
        if image.ndim != 4 or image.shape[0] != 1:
            raise ModelConfigError(f'OrtNetwork: expected a (1, C, H, W) batch, got '
                                   f'{tuple(image.shape)}')
        sess = self.session(image.shape[2], image.shape[3])
        x = image.detach().float().contiguous().numpy()
        out = sess.run(list(OUTPUTS), {'image': x})
        return {k: torch.from_numpy(v) for k, v in zip(OUTPUTS, out)}
