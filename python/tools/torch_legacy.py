"""Read a PyTorch checkpoint of the legacy (non-zip) format into numpy arrays, without PyTorch.

    from torch_legacy import load_state_dict
    state = load_state_dict("efficientnet-lite1-77cc7160.pth")   # {name: np.ndarray}

The legacy format (`torch.save(..., _use_new_zipfile_serialization=False)`, torch/serialization.py
`_legacy_save`): five pickles one after another (the magic number 0x1950a86a20f9469cfc6c, the protocol
version 1001, a dict of system information, the object itself, and the list of storage keys in the order their
data follows), then each storage's data: its element count as a little-endian int64 and the elements'
little-endian bytes. In the object's pickle a storage is a persistent id ('storage', storage class, key,
location, element count, view metadata) and a tensor is torch._utils._rebuild_tensor_v2(storage, offset,
size, stride, requires_grad, backward hooks).

Unpickling runs only what an allow-list names (the classes a state dict of tensors needs: OrderedDict, the
tensor rebuild function, the storage classes); anything else is refused, so a file cannot run code here.
"""

from __future__ import annotations

import collections
import io
import pickle
import struct
from pathlib import Path

import numpy as np

MAGIC = 0x1950A86A20F9469CFC6C
PROTOCOL = 1001
# storage class -> element type
STORAGES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16, "LongStorage": np.int64,
    "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8, "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


class _Storage:
    def __init__(self, dtype, key: str, numel: int):
        self.dtype, self.key, self.numel, self.data = np.dtype(dtype), key, numel, None


class _Tensor:
    """A tensor to be made once its storage's data is read."""

    def __init__(self, storage: _Storage, offset: int, size, stride):
        self.storage, self.offset, self.size, self.stride = storage, offset, tuple(size), tuple(stride)

    def array(self) -> np.ndarray:
        data = self.storage.data
        if self.size and self.offset + sum((n - 1) * s for n, s in zip(self.size, self.stride)) >= len(data):
            raise ValueError(f"tensor of size {self.size} and stride {self.stride} at {self.offset} overruns its storage of {len(data)}")
        item = data.itemsize
        view = np.lib.stride_tricks.as_strided(data[self.offset:], shape=self.size, strides=[s * item for s in self.stride])
        return np.array(view)  # a copy: contiguous, owns its memory


def _rebuild_tensor_v2(storage, offset, size, stride, requires_grad=False, backward_hooks=None, metadata=None):
    return _Tensor(storage, offset, size, stride)


class _Unpickler(pickle.Unpickler):
    def __init__(self, f, storages: dict):
        super().__init__(f)
        self.storages = storages

    def find_class(self, module, name):
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor_v2
        if module == "torch" and name in STORAGES:
            return name
        raise pickle.UnpicklingError(f"{module}.{name} is not allowed in a state dict of tensors")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and pid and pid[0] == "storage" and len(pid) >= 5):
            raise pickle.UnpicklingError(f"unexpected persistent id {pid!r}")
        kind, key, _location, numel = pid[1], pid[2], pid[3], pid[4]
        if len(pid) > 5 and pid[5] is not None:
            raise pickle.UnpicklingError("storage views are not supported")
        if kind not in STORAGES:
            raise pickle.UnpicklingError(f"storage class {kind!r} is not supported")
        if key not in self.storages:
            self.storages[key] = _Storage(STORAGES[kind], key, int(numel))
        return self.storages[key]


def load_state_dict(path) -> dict[str, np.ndarray]:
    """The tensors of a legacy-format checkpoint holding a (possibly nested under 'state_dict') dict of tensors."""
    raw = Path(path).read_bytes()
    f = io.BytesIO(raw)

    def plain():
        return _Unpickler(f, {}).load()

    if plain() != MAGIC:
        raise ValueError(f"{path}: not a legacy PyTorch checkpoint (no magic number; a zip checkpoint needs another reader)")
    if plain() != PROTOCOL:
        raise ValueError(f"{path}: unknown legacy protocol version")
    plain()  # system information: endianness and type sizes
    storages: dict[str, _Storage] = {}
    obj = _Unpickler(f, storages).load()
    keys = plain()
    for key in keys:
        s = storages.get(key)
        if s is None:
            raise ValueError(f"{path}: storage {key!r} listed but not used")
        (count,) = struct.unpack("<q", f.read(8))
        if count != s.numel:
            raise ValueError(f"{path}: storage {key!r} holds {count} elements, the object says {s.numel}")
        nbytes = count * s.dtype.itemsize
        chunk = f.read(nbytes)
        if len(chunk) != nbytes:
            raise ValueError(f"{path}: storage {key!r} is cut short ({len(chunk)} of {nbytes} bytes)")
        s.data = np.frombuffer(chunk, dtype=s.dtype.newbyteorder("<"))
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: holds a {type(obj).__name__}, not a dict of tensors")
    out = {}
    for name, t in obj.items():
        if not isinstance(t, _Tensor):
            raise ValueError(f"{path}: entry {name!r} is a {type(t).__name__}, not a tensor")
        if t.storage.data is None:
            raise ValueError(f"{path}: the data of {name!r} is missing")
        out[name] = t.array()
    return out
