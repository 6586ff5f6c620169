"""Shape-keyed CUDA-graph replay of a forward pass.

VGGT at a few views is launch-bound: thousands of small kernels for a few TFLOP of
work. Capturing the whole forward once per input shape (and autocast setting) and
replaying it removes the per-kernel CPU cost. This works because the forward makes no
host<->device copies and no synchronisations (every constant is built on the device
from Python integers).
"""

from __future__ import annotations

import contextlib
import logging
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import torch

logger = logging.getLogger(__name__)

# Eager runs before capture: lazy CUDA/cuBLAS initialisation, cuDNN autotuning and
# torch.compile all happen there, never inside the capture.
WARMUP_RUNS = 2

Outputs = dict[str, "torch.Tensor | list[torch.Tensor]"]


@dataclass
class _Captured:
    graph: torch.cuda.CUDAGraph
    static_input: torch.Tensor
    static_outputs: Outputs


def _on(device: torch.device):
    """Make ``device`` current (streams and graphs belong to the current CUDA device)."""
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()


def _clone(outputs: Outputs) -> Outputs:
    """Fresh copies of the static outputs (the next replay overwrites them); a tensor
    that appears twice (``pose_enc`` is ``pose_enc_list[-1]``) is copied once."""
    copies: dict[int, torch.Tensor] = {}

    def copy(t: torch.Tensor) -> torch.Tensor:
        if id(t) not in copies:
            copies[id(t)] = t.clone()
        return copies[id(t)]

    return {k: [copy(t) for t in v] if isinstance(v, list) else copy(v) for k, v in outputs.items()}


class CudaGraphCache:
    """Captured graphs of ``fn(images) -> dict of tensors``, at most ``capacity`` shapes (LRU).

    The key is the input's shape, dtype and device plus the CUDA autocast state (and
    inference mode), so a graph always replays exactly the computation an eager call
    would run. A shape
    whose capture fails is remembered and runs eagerly from then on.
    """

    def __init__(self, capacity: int = 2) -> None:
        self.capacity = capacity
        self._graphs: OrderedDict[tuple, _Captured] = OrderedDict()
        self._uncapturable: set[tuple] = set()

    def __len__(self) -> int:
        return len(self._graphs)

    def clear(self) -> None:
        """Forget every graph (needed when the model's tensors move or are replaced)."""
        for entry in self._graphs.values():
            entry.graph.reset()
        self._graphs.clear()
        self._uncapturable.clear()

    def run(self, fn: Callable[[torch.Tensor], Outputs], images: torch.Tensor) -> Outputs:
        """``fn(images)`` through a cached graph (captured on first use of this key)."""
        autocast = (torch.is_autocast_enabled("cuda"), torch.get_autocast_dtype("cuda"))
        # Inference mode is in the key: its (inference) static tensors cannot be
        # written to outside it.
        key = (tuple(images.shape), images.dtype, images.device, autocast, torch.is_inference_mode_enabled())
        if key in self._uncapturable:
            return fn(images)
        entry = self._graphs.get(key)
        if entry is None:
            try:
                entry = self._capture(fn, images, autocast)
            except RuntimeError as exc:
                logger.warning("CUDA graph capture failed for input %s (%s); running eagerly", key[0], exc)
                self._uncapturable.add(key)
                return fn(images)
            self._graphs[key] = entry
            while len(self._graphs) > self.capacity:
                _, evicted = self._graphs.popitem(last=False)
                evicted.graph.reset()
        self._graphs.move_to_end(key)
        with _on(images.device):
            entry.static_input.copy_(images)
            entry.graph.replay()
            return _clone(entry.static_outputs)

    @staticmethod
    def _capture(fn, images: torch.Tensor, autocast: tuple[bool, torch.dtype]) -> _Captured:
        enabled, dtype = autocast
        static_input = images.clone()

        def call() -> Outputs:
            # Autocast's weight-cast cache must be off: cached casts made during warm-up
            # would be freed after it while the graph still points at them.
            with torch.autocast("cuda", dtype=dtype, enabled=enabled, cache_enabled=False):
                return fn(static_input)

        with _on(images.device):
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(WARMUP_RUNS):
                    call()
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                static_outputs = call()
        return _Captured(graph, static_input, static_outputs)
