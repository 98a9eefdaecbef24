"""How much work one batch of torch ops may hold: the chunk size of the chunked hot loops.

The multi-view sweep, the TV cost volume and the exact fusion process pixels in chunks so the
largest intermediate tensor stays below a budget (``chunk_elements``, float elements). On a CPU
that budget also keeps the working set in cache. On a GPU memory is plentiful and every extra
chunk costs another round of kernel launches, which dominate there (an H100 computes the
multi-view sweep of a 320x240 keyframe in under 1 ms of kernel time, but 4 M-element chunks
took 850 launches and 23 ms): a CUDA device gets at least :data:`CUDA_CHUNK_ELEMENTS`.
Results do not depend on the chunk size (every chunk is computed the same way).
"""

from __future__ import annotations

import torch

#: Minimum chunk budget on an accelerator: 64 M floats = 256 MB per largest intermediate.
CUDA_CHUNK_ELEMENTS = 1 << 26


def effective_chunk_elements(requested: int, device: str | torch.device) -> int:
    """The configured budget on a CPU; at least :data:`CUDA_CHUNK_ELEMENTS` elsewhere."""
    if torch.device(device).type == 'cpu':
        return int(requested)
    return max(int(requested), CUDA_CHUNK_ELEMENTS)
