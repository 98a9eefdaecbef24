"""Each search row's bucket as one index (into ``filter_buckets.search_buckets``), what the
bucket tests assert on; the package itself only needs the rows of each bucket."""

from __future__ import annotations

import torch

from depth_fusion_ros.multiview.filter_buckets import bucket_members
from depth_fusion_ros.multiview.filter_config import FilterConfig


def plan_buckets(span_px: torch.Tensor, fresh: torch.Tensor, config: FilterConfig) -> torch.Tensor:
    """Bucket index of each row: ``filter_buckets.bucket_members`` as one index per row."""
    bucket = torch.empty_like(span_px, dtype=torch.long)
    for k, rows in enumerate(bucket_members(span_px, fresh, config)):
        bucket.index_fill_(0, rows, k)
    return bucket
