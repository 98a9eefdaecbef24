"""``sensor_msgs/PointCloud2`` <-> numpy: unorganised float32 x, y, z clouds with PCL's packed rgb."""

from __future__ import annotations

from typing import Any

import numpy as np

from .message_kinds import as_kind
from .message_stamps import _header_for

#: ``sensor_msgs/PointField.FLOAT32``
POINTFIELD_FLOAT32 = 7


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """``(N, 3) uint8`` colours as PCL's packed ``rgb`` float32 (bits ``0x00RRGGBB``)."""
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3).astype(np.uint32)
    return ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)


def pointcloud2_msg(xyz: np.ndarray, header: Any, *, kind: Any, rgb: np.ndarray | None = None) -> Any:
    """An unorganised ``sensor_msgs/PointCloud2`` with float32 fields x, y, z (+ packed rgb).

    ``xyz`` is ``(N, 3)`` in the header's frame; ``rgb`` an optional ``(N, 3) uint8``.
    """
    k = as_kind(kind)
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    names = ['x', 'y', 'z']
    columns = [xyz]
    if rgb is not None:
        rgb = np.asarray(rgb)
        if rgb.reshape(-1, 3).shape[0] != len(xyz):
            raise ValueError(f'rgb has {rgb.reshape(-1, 3).shape[0]} points, xyz has {len(xyz)}')
        names.append('rgb')
        columns.append(pack_rgb(rgb)[:, None])
    points = np.ascontiguousarray(np.hstack(columns), dtype='<f4')
    point_step = 4 * len(names)
    fields = [
        k.new('sensor_msgs/msg/PointField', name=n, offset=4 * i, datatype=POINTFIELD_FLOAT32, count=1)
        for i, n in enumerate(names)
    ]
    return k.new(
        'sensor_msgs/msg/PointCloud2',
        header=_header_for(header, k),
        height=1,
        width=len(xyz),
        fields=fields,
        is_bigendian=False,
        point_step=point_step,
        row_step=point_step * len(xyz),
        data=k.uint8_array(points.tobytes()),
        is_dense=bool(np.all(np.isfinite(xyz))),
    )


def pointcloud2_to_numpy(msg: Any) -> dict[str, np.ndarray]:
    """The float32 fields of a little-endian ``PointCloud2`` as ``{name: (N,) array}``.

    ``rgb`` is returned unpacked as ``(N, 3) uint8``. Only FLOAT32 fields are supported (that
    is what ``pointcloud2_msg`` writes and what depth clouds use).
    """
    if msg.is_bigendian:
        raise ValueError('big-endian PointCloud2 is not supported')
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size < n * step:
        raise ValueError(f'PointCloud2 data has {buf.size} bytes, expected {n * step}')
    rows = buf[: n * step].reshape(n, step)
    out: dict[str, np.ndarray] = {}
    for f in msg.fields:
        if int(f.datatype) != POINTFIELD_FLOAT32:
            raise ValueError(
                f'PointCloud2 field {f.name!r} has datatype {f.datatype}, only FLOAT32 is supported'
            )
        col = np.ascontiguousarray(rows[:, f.offset : f.offset + 4]).view('<f4').ravel()
        if f.name == 'rgb':
            bits = col.view(np.uint32)
            col = np.stack(((bits >> 16) & 255, (bits >> 8) & 255, bits & 255), axis=1).astype(np.uint8)
        out[f.name] = col
    return out
