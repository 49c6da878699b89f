"""openpi's msgpack-numpy encoding (openpi_client/msgpack_numpy.py), as inference/src/msgpack_numpy.rs
reads and writes it: an array travels as {b"__ndarray__": True, b"data": raw C-order bytes,
b"dtype": numpy dtype.str, b"shape": [...]}, a numpy scalar as {b"__npgeneric__": True, b"data",
b"dtype"}; the marker keys are bytes (msgpack bin), ordinary keys str."""

import msgpack
import numpy as np


def _pack(obj):
    if isinstance(obj, (np.ndarray, np.generic)) and obj.dtype.kind in "VOc":
        raise ValueError(f"unsupported dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        obj = np.ascontiguousarray(obj)
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": list(obj.shape)}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


def _unpack(obj):
    if b"__ndarray__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in "VOc":
            raise ValueError(f"unsupported dtype {dtype}")
        return np.frombuffer(obj[b"data"], dtype).reshape(obj[b"shape"])
    if b"__npgeneric__" in obj:
        return np.dtype(obj[b"dtype"]).type(obj[b"data"])
    return obj


def packb(obj) -> bytes:
    return msgpack.packb(obj, default=_pack)


def unpackb(data: bytes):
    return msgpack.unpackb(data, object_hook=_unpack)
