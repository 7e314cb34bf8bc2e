"""Scan meshes and their landmarks.

read_scan: any mesh trimesh reads (OBJ, PLY, STL, OFF, GLB/glTF); scenes and several
components are merged into one triangle mesh, units and orientation are left as they are
(calibration handles them).

read_landmarks: MPEG-4 feature point name -> scan coordinates, from
- JSON `{"9.3": [x, y, z], ...}` or `{"9.3": 1234, ...}` (0-based index into the scan
  file's own vertex list: an OBJ's `v` lines in order, unused ones too), also under a
  top-level "landmarks" key;
- menpo `.ljson` with 68 iBUG points: version 3 (groups -> <name> -> landmarks -> points;
  the group with 68 points when there are several), version 2 (landmarks -> points) and
  version 1 (groups -> [landmarks -> [{point}]]);
- CSV: rows `name,x,y,z` (MPEG-4 names), or 68 rows `x,y,z` in iBUG order; an optional
  header row, `#` comments and blank lines.
Names are the standard's 84 feature points, each given once. Text files may start with a
UTF-8 byte-order mark (spreadsheets and Windows editors write one). iBUG-68 points are
turned into FDPs by IBUG68_TO_FDP (below).
"""

from __future__ import annotations

import csv
import json
import os
import re

from typing import Callable

import numpy as np

from fae.mpeg4 import FEATURE_POINTS

# iBUG 300-W 68-point markup (0-based) -> MPEG-4 FDP. Values are the iBUG indices whose
# mean is the FDP. iBUG's "right" is the subject's right; MPEG-4 "left" is the face's own
# left (+x). Points without a clear MPEG-4 counterpart (jaw contour 0-2, 4-6, 10-12, 14-16,
# nose bridge 27-29) are not used.
IBUG68_TO_FDP: dict[str, tuple[int, ...]] = {
    "2.1": (8,),            # bottom of the chin
    "2.11": (9,),           # chin left corner
    "2.12": (7,),           # chin right corner
    "2.13": (13,),          # left corner of jaw bone
    "2.14": (3,),           # right corner of jaw bone
    "4.1": (22,),           # right (inner) corner of left eyebrow
    "4.3": (24,),           # uppermost point of left eyebrow
    "4.5": (26,),           # left (outer) corner of left eyebrow
    "4.2": (21,),           # left (inner) corner of right eyebrow
    "4.4": (19,),           # uppermost point of right eyebrow
    "4.6": (17,),           # right (outer) corner of right eyebrow
    "9.3": (30,),           # nose tip
    "9.15": (33,),          # bottom middle edge of nose
    "9.1": (35,),           # left nostril border
    "9.2": (31,),           # right nostril border
    "9.5": (34,),           # bottom left edge of nose
    "9.4": (32,),           # bottom right edge of nose
    "3.12": (36,),          # right corner of right eye (outer)
    "3.14": (37, 38),       # upper outer right eyelid
    "3.8": (39,),           # left corner of right eye (inner)
    "3.10": (40, 41),       # lower outer right eyelid
    "3.11": (42,),          # right corner of left eye (inner)
    "3.13": (43, 44),       # upper outer left eyelid
    "3.7": (45,),           # left corner of left eye (outer)
    "3.9": (46, 47),        # lower outer left eyelid
    "8.4": (48,),           # right corner of outer lip contour
    "8.6": (49, 50),        # between 8.4 and 8.1, outer upper lip
    "8.9": (50,),           # right high point of Cupid's bow
    "8.1": (51,),           # middle of outer upper lip
    "8.10": (52,),          # left high point of Cupid's bow
    "8.5": (52, 53),        # between 8.3 and 8.1, outer upper lip
    "8.3": (54,),           # left corner of outer lip contour
    "8.7": (55, 56),        # between 8.3 and 8.2, outer lower lip
    "8.2": (57,),           # middle of outer lower lip
    "8.8": (58, 59),        # between 8.4 and 8.2, outer lower lip
    "2.5": (60,),           # right corner of inner lip contour
    "2.7": (61,),           # inner upper lip, between 2.2 and 2.5
    "2.2": (62,),           # middle of inner upper lip
    "2.6": (63,),           # inner upper lip, between 2.2 and 2.4
    "2.4": (64,),           # left corner of inner lip contour
    "2.8": (65,),           # inner lower lip, between 2.3 and 2.4
    "2.3": (66,),           # middle of inner lower lip
    "2.9": (67,),           # inner lower lip, between 2.3 and 2.5
}

_FDP_NAME = re.compile(r"^(\d{1,2})\.(\d{1,2})$")
_FDP_NAMES = frozenset(p.name for p in FEATURE_POINTS)
_CSV_HEADERS = ("name", "fdp", "point", "x")


class LandmarkError(ValueError):
    """A landmark file that cannot be read; the message names the file and field."""


# what trimesh misreads in an OBJ: a tab between fields, a negative (relative) index on a
# face, a line indented, a comment after an element, a byte-order mark
_OBJ_MISREAD = re.compile(rb"\t|^[ \t]*[flp][ \t][^\n]*[ \t/]-\d|^ +\S|^[ \t]*(?:v|vt|vn|f|l)[ \t][^\n#]*#|"
                          rb"\A\xef\xbb\xbf", re.MULTILINE)
_OBJ_ELEMENTS = {"v": 0, "vt": 1, "vn": 2}  # the elements a face's index triplet counts


def _absolute(index: str, count: int, line: int) -> str:
    """An OBJ index as written, absolute: a negative one counts back from `count` elements
    (the ones read before its line, 1-based `line`). Raises ValueError for one that counts
    back past the first element, and for 0 (the format counts from 1)."""
    if index.startswith("-") and index[1:].isdigit():
        if int(index) < -count:
            raise ValueError(f"line {line}: index {index} counts back past the {count} elements before it")
        return str(count + int(index) + 1)
    if index == "0":
        raise ValueError(f"line {line}: index 0 (OBJ counts from 1)")
    return index


def _obj_as_read(data: bytes) -> bytes:
    """OBJ text with single spaces between fields, no byte-order mark, no comments after
    elements, and every face's and line's indices absolute: a negative index counts back
    from the elements read so far (the format's relative indices), -1 the last. Raises
    ValueError naming the line of an index that names no element."""
    counts = [0, 0, 0]
    out = []
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    for number, raw in enumerate(data.split(b"\n"), start=1):
        line = raw.decode("utf-8", errors="surrogateescape")
        fields = line.split("#", 1)[0].split() if line.lstrip()[:1] in ("v", "f", "l", "p") else line.split()
        if not fields:
            out.append(raw.strip(b" \t\r"))
            continue
        key = fields[0]
        if key in _OBJ_ELEMENTS:
            counts[_OBJ_ELEMENTS[key]] += 1
        elif key in ("f", "l", "p"):
            fields = [key] + ["/".join(_absolute(x, counts[k], number) if k < 3 else x
                                       for k, x in enumerate(corner.split("/")))
                              for corner in fields[1:]]
        elif key not in ("vp",):  # a name (a material, a group) keeps its own spacing
            rest = line.strip()[len(key):].strip()
            out.append(f"{key} {rest}".rstrip().encode("utf-8", errors="surrogateescape"))
            continue
        out.append(" ".join(fields).encode("utf-8", errors="surrogateescape"))
    return b"\n".join(out)


def mesh_source(path: str) -> tuple[object, dict]:
    """What trimesh.load is to read for the mesh file `path`, and the keywords that go with
    it: the path itself, or, for an OBJ with a tab between fields or an indented face (read
    as a file without triangles), relative (negative) indices, which the format allows, or
    a byte-order mark (read as the wrong vertices, silently), or a comment after an element,
    a copy as trimesh reads it (_obj_as_read) in memory, with the folder beside the file to
    find what it names (its materials and their textures)."""
    import io

    import trimesh

    if os.path.splitext(path)[1].lower() != ".obj":
        return path, {}
    with open(path, "rb") as fh:
        data = fh.read()
    if not _OBJ_MISREAD.search(data):
        return path, {}
    return io.BytesIO(_obj_as_read(data)), {
        "file_type": "obj", "resolver": trimesh.resolvers.FilePathResolver(os.path.abspath(path))}


def read_scan(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """V (n, 3) float64 in the file's unit and frame, F (m, 3) int64, all components merged."""
    import trimesh

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: scan file not found")
    expected = "expected a mesh file (OBJ, PLY, STL, OFF, GLB/glTF)"
    try:
        source, how = mesh_source(path)
        loaded = trimesh.load(source, force="mesh", process=False, **how)
    except ImportError:  # a loader wanting an optional module for bytes it cannot place
        raise ValueError(f"{path}: cannot read a mesh: {expected}") from None
    except FileNotFoundError as exc:  # a file the mesh refers to (a .gltf's buffers)
        missing = exc.filename or (exc.args[0] if exc.args else exc)
        name = " ".join(str(missing).split())[:200]
        raise ValueError(f"{path}: cannot read a mesh: it refers to {name}, which is not beside it "
                         f"({os.path.dirname(os.path.abspath(path))})") from None
    except Exception as exc:  # trimesh raises many kinds
        reason = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise ValueError(f"{path}: cannot read a mesh ({reason}): {expected}") from None
    V = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    F = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if len(V) == 0 or len(F) == 0:
        raise ValueError(f"{path}: the file holds no triangles (point clouds are not supported)")
    if not np.all(np.isfinite(V)):
        raise ValueError(f"{path}: vertex coordinates contain NaN or infinity")
    if F.min() < 0 or F.max() >= len(V):
        bad = int(F.max() if F.max() >= len(V) else F.min())
        raise ValueError(f"{path}: a face names vertex {bad}; the file has {len(V)} (expected 0..{len(V) - 1})")
    return V, F


def indexed_vertices(path: str | os.PathLike, V: np.ndarray) -> np.ndarray:
    """(k, 3) the vertices a landmark file's vertex indices count, in the scan file's own
    order: an OBJ's `v` lines, unused ones too (read_scan's V has a vertex per texture
    seam copy, none unused, and a file's materials one after another, so its indices are
    not the file's); V for other formats, which read_scan keeps in the file's order."""
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() != ".obj":
        return V
    try:  # the `v` lines themselves: a reader joins a file's materials as pieces of its own order
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            rows = [fields[1:4] for fields in map(str.split, fh) if fields[:1] == ["v"]]
        return np.array(rows, dtype=np.float64).reshape(-1, 3)
    except (OSError, ValueError):  # read_scan read it; the same lines can only fail as oddly
        return V


def ibug68_to_fdp(points: np.ndarray, source: str = "landmarks") -> dict[str, np.ndarray]:
    """FDP name -> (3,) from 68 iBUG points (68, 3), by IBUG68_TO_FDP.

    Raises LandmarkError naming the points that are null or not finite among those used
    (a feature point silently missing would bend the fit where nobody looks)."""
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (68, 3):
        raise LandmarkError(f"{source}: expected 68 iBUG points with x, y, z, got shape {points.shape}")
    used = sorted({i for idx in IBUG68_TO_FDP.values() for i in idx})
    missing = [i for i in used if not np.all(np.isfinite(points[i]))]
    if missing:
        shown = ", ".join(str(i) for i in missing[:10]) + (", ..." if len(missing) > 10 else "")
        raise LandmarkError(f"{source}: {len(missing)} iBUG points are null or not finite (0-based: {shown}); "
                            "expected x, y, z numbers for every point fae uses")
    return {name: points[list(idx)].mean(axis=0) for name, idx in IBUG68_TO_FDP.items()}


def _check_name(name: str, source: str) -> str:
    name = str(name).strip()
    m = _FDP_NAME.match(name)
    if not m or not 2 <= int(m.group(1)) <= 11:
        raise LandmarkError(f"{source}: {name!r} is not an MPEG-4 feature point name (expected group.index, e.g. \"9.3\")")
    name = f"{int(m.group(1))}.{int(m.group(2))}"
    if name not in _FDP_NAMES:
        raise LandmarkError(f"{source}: {name!r} is not one of the standard's 84 feature points (groups 2-11: 2.1..2.14, "
                            "3.1..3.14, 4.1..4.6, 5.1..5.4, 6.1..6.4, 7.1, 8.1..8.10, 9.1..9.15, 10.1..10.10, 11.1..11.6)")
    return name


def _point(value, name: str, source: str, vertices: Callable[[], np.ndarray | None]) -> np.ndarray:
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        vertices = vertices()
        if vertices is None:
            raise LandmarkError(f"{source}: field {name!r} is a vertex index but no scan vertices were given")
        if not 0 <= value < len(vertices):
            raise LandmarkError(f"{source}: field {name!r}: vertex index {value} outside 0..{len(vertices) - 1}")
        return np.asarray(vertices[value], dtype=np.float64)
    try:  # a string or a list inside the list is no coordinate (numpy's own words named neither file nor field)
        arr = np.asarray(value, dtype=np.float64) if isinstance(value, (list, tuple)) else None
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise LandmarkError(f"{source}: field {name!r}: expected [x, y, z] (3 finite numbers) or a vertex index, got {value!r}")
    return arr


def read_landmarks(path: str | os.PathLike,
                   vertices: np.ndarray | Callable[[], np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """FDP name -> (3,) float64 in the scan's frame and unit (see module docstring).

    vertices: the scan file's own vertices (k, 3) (indexed_vertices), or a function giving
    them (called only when the file gives a vertex index); needed for vertex indices.
    Raises LandmarkError naming the file (and line or field) for any content it cannot use.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: landmark file not found")
    cache: list = []

    def scan_vertices():
        if not cache:
            cache.append(vertices() if callable(vertices) else vertices)
        return cache[0]

    try:
        return _read_landmarks(path, scan_vertices)
    except UnicodeDecodeError as exc:
        raise LandmarkError(f"{path}: byte {exc.start}: expected UTF-8 text") from None
    except RecursionError:
        raise LandmarkError(f"{path}: nested too deeply; expected a JSON object of feature points") from None


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """A JSON object that names a key twice is an error, not its last value (json's way)."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise LandmarkError(f"field {key!r} is given twice")
        out[key] = value
    return out


def _ljson_points(path: str, groups) -> np.ndarray:
    """(p, 3) the points of the menpo ljson `groups`: in version 3 (an object of groups) the
    group with 68 points when there are several, else the first; in version 1 (a list of
    labelled parts of one set, each point {"point": [x, y, z]}) all of them in order."""
    found = list(groups.values()) if isinstance(groups, dict) else groups if isinstance(groups, list) else None
    if not found:
        raise LandmarkError(f"{path}: ljson field groups: expected an object of landmark groups")
    sets = []
    for group in found:
        try:
            points = group["landmarks"]
            # version 1 lists each point as {"point": [x, y, z]}, version 3 holds them in "points"
            points = [p["point"] for p in points] if isinstance(points, list) else points["points"]
            sets.append(np.array([[np.nan if c is None else c for c in p] for p in points], dtype=np.float64))
        except (KeyError, TypeError, ValueError, OverflowError):
            sets.append(None)
    usable = [p for p in sets if p is not None and p.ndim == 2 and p.shape[1] == 3]
    if not usable:
        raise LandmarkError(f"{path}: ljson field groups.<name>.landmarks.points missing or malformed")
    if len(usable) == len(found) and all(isinstance(g.get("landmarks"), list) for g in found):
        # version 1: the groups are labelled parts of one set (jaw, brows, nose, eyes, mouth), in order
        return np.concatenate(usable)
    return next((p for p in usable if len(p) == 68), usable[0])


def _read_landmarks(path: str, vertices: Callable[[], np.ndarray | None]) -> dict[str, np.ndarray]:
    ext = os.path.splitext(path)[1].lower()
    if ext in (".json", ".ljson"):
        try:
            with open(path, encoding="utf-8-sig") as fh:
                data = json.load(fh, object_pairs_hook=_unique_keys)
        except json.JSONDecodeError as exc:
            raise LandmarkError(f"{path}: line {exc.lineno}: not valid JSON ({exc.msg})") from exc
        except LandmarkError as exc:
            raise LandmarkError(f"{path}: {exc}") from None
        except (ValueError, OverflowError) as exc:  # a number too long or too large for a float
            raise LandmarkError(f"{path}: not usable JSON ({exc})") from None
        if isinstance(data, dict) and "groups" in data:  # menpo ljson, version 3 or 1
            return ibug68_to_fdp(_ljson_points(path, data["groups"]), path)
        if isinstance(data, dict) and isinstance(data.get("landmarks"), dict) and "points" in data["landmarks"]:
            return ibug68_to_fdp(_ljson_points(path, [data]), path)  # menpo ljson version 2: one group
        if isinstance(data, dict) and isinstance(data.get("landmarks"), dict):
            data = data["landmarks"]
        if not isinstance(data, dict) or not data:
            raise LandmarkError(f"{path}: expected a JSON object mapping feature point names to [x, y, z] or vertex indices")
        out = {}
        for key, value in data.items():
            name = _check_name(key, path)
            if name in out:  # "9.3" and "09.3" are one point
                raise LandmarkError(f"{path}: feature point {name} is given twice")
            try:
                out[name] = _point(value, key, path, vertices)
            except OverflowError:
                raise LandmarkError(f"{path}: field {key!r}: expected [x, y, z] (3 finite numbers) or a vertex index, "
                                    f"got a number too large") from None
        return out
    if ext in (".csv", ".txt"):
        with open(path, encoding="utf-8-sig", newline="") as fh:
            reader = csv.reader(fh)
            rows = [(reader.line_num, r) for r in reader if r and any(c.strip() for c in r)
                    and not r[0].lstrip().startswith("#")]
        if rows and (rows[0][1][0].strip().lower() in _CSV_HEADERS  # a header row: a name's column, or x, y, z
                     or [c.strip().lower() for c in rows[0][1][-3:]] == ["x", "y", "z"]):
            rows = rows[1:]
        if rows and all(len(r) == 3 for _, r in rows):
            try:
                pts = np.array([r for _, r in rows], dtype=np.float64)
            except ValueError as exc:
                raise LandmarkError(f"{path}: expected numbers in every x, y, z row ({exc})") from exc
            if len(pts) != 68:
                raise LandmarkError(f"{path}: {len(pts)} unnamed x, y, z rows; unnamed rows must be the 68 iBUG points (use name,x,y,z rows for MPEG-4 names)")
            return ibug68_to_fdp(pts, path)
        out, first_line = {}, {}
        for line, r in rows:
            if len(r) != 4:
                raise LandmarkError(f"{path}: line {line}: expected name,x,y,z, got {len(r)} fields")
            try:
                point = np.array(r[1:], dtype=np.float64)
            except ValueError as exc:
                raise LandmarkError(f"{path}: line {line}: x, y, z must be numbers") from exc
            if not np.all(np.isfinite(point)):
                raise LandmarkError(f"{path}: line {line}: x, y, z must be finite numbers, got {', '.join(r[1:])}")
            name = _check_name(r[0], f"{path}: line {line}")
            if name in out:
                raise LandmarkError(f"{path}: line {line}: feature point {name} is given twice (first on line "
                                    f"{first_line[name]})")
            out[name], first_line[name] = point, line
        return out
    raise LandmarkError(f"{path}: unknown landmark format {ext!r} (expected .json, .ljson or .csv)")
