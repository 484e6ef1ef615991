"""Files between the Blender add-on and meshseq, in plain Python (``struct``/``array``, no numpy).

PC2 point caches (the object's animation out, meshseq's results in), the OBJ base mesh beside a
cache, and the binary PLY frames meshseq writes for several samples. Part of the add-on zip
(``meshseq_blender/cachefiles.py``); it needs no ``bpy``, so tests import it directly.
"""

import array
import os
import struct
import sys

PC2_HEADER = struct.Struct("<12siiffi")  # magic, version, points, start frame, sample rate, samples
PC2_MAGIC = b"POINTCACHE2\0"


class AddonError(Exception):
    """A user-facing problem, shown as one report line."""




def _little_endian(values: array.array) -> bytes:
    if sys.byteorder != "little":
        values = array.array(values.typecode, values)
        values.byteswap()
    return values.tobytes()


def write_pc2(path: str, frames: list, n_points: int) -> None:
    """Write ``frames`` (T arrays of 3 * n_points float32) as a PC2 file, start frame 0, rate 1."""
    with open(path, "wb") as fh:
        fh.write(PC2_HEADER.pack(PC2_MAGIC, 1, n_points, 0.0, 1.0, len(frames)))
        for co in frames:
            fh.write(_little_endian(co))


def read_pc2(path: str) -> list:
    """The frames of a PC2 file: a list of T arrays ('f') of 3 * points floats."""
    with open(path, "rb") as fh:
        data = fh.read()
    if len(data) < PC2_HEADER.size or data[:11] != PC2_MAGIC[:11]:
        raise AddonError(f"{path}: not a PC2 file")
    _magic, _version, points, _start, _rate, samples = PC2_HEADER.unpack_from(data)
    size = 12 * points
    if points < 1 or samples < 1 or len(data) != PC2_HEADER.size + size * samples:
        raise AddonError(f"{path}: PC2 file of {len(data)} bytes does not hold {samples} samples of {points} points")
    frames = []
    for t in range(samples):
        co = array.array("f")
        co.frombytes(data[PC2_HEADER.size + t * size: PC2_HEADER.size + (t + 1) * size])
        if sys.byteorder != "little":
            co.byteswap()
        frames.append(co)
    return frames


def write_obj(path: str, co: array.array, triangles: list) -> None:
    """An OBJ base mesh: vertices ``co`` (3 V floats, written exactly) and triangles (0-based)."""
    lines = ["# meshseq add-on base mesh\n"]
    lines += ["v %r %r %r\n" % (co[i], co[i + 1], co[i + 2]) for i in range(0, len(co), 3)]
    lines += ["f %d %d %d\n" % (a + 1, b + 1, c + 1) for a, b, c in triangles]
    with open(path, "w") as fh:
        fh.write("".join(lines))


def read_ply_vertices(path: str) -> array.array:
    """Vertex positions (3 V floats) of one binary little-endian PLY frame that meshseq wrote."""
    with open(path, "rb") as fh:
        data = fh.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise AddonError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", "replace").split("\n")
    if "format binary_little_endian 1.0" not in header:
        raise AddonError(f"{path}: expected a binary little-endian PLY (as meshseq writes)")
    n = next((int(h.split()[2]) for h in header if h.startswith("element vertex ")), None)
    props = [h for h in header if h.startswith("property ")][:3]
    if n is None or props != ["property double x", "property double y", "property double z"]:
        raise AddonError(f"{path}: expected vertices of three doubles x, y, z (as meshseq writes)")
    co = array.array("d")
    co.frombytes(data[end + 11: end + 11 + 24 * n])
    if sys.byteorder != "little":
        co.byteswap()
    return array.array("f", co)


def read_ply_folder(folder: str) -> list:
    """The frames (arrays of 3 V floats) of a folder of PLY frames, in file-name order."""
    names = sorted(n for n in os.listdir(folder) if n.endswith(".ply"))
    if not names:
        raise AddonError(f"{folder}: meshseq wrote no PLY frames")
    return [read_ply_vertices(os.path.join(folder, n)) for n in names]
