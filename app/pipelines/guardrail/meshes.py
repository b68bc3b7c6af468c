"""Mesh helpers for reconstructed guardrails: plain (vertices (V, 3) float64, faces (F, 3)
int64) pairs, circles swept along polylines (pipes, poles), a section swept along a path
(beams), and the export of one guardrail as glTF binary and PLY through trimesh, OBJ text
written a block of rows at a time.

World coordinates can be large (UTM: millions of metres) and glTF and PLY store float32
vertices, which would round them to decimetres. Exports therefore keep vertices relative to an
`origin` where the format cannot hold doubles: the glTF node carries the origin as its
translation (JSON numbers, full precision), the PLY header names it in a comment
(`origin X Y Z`: world = vertex + origin), and OBJ (text) holds world coordinates as they are.
Files are written under a temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import trimesh
from trimesh.util import array_to_string

from app.geometry.mesh_grid import cap_faces, grid_faces

Mesh = tuple[np.ndarray, np.ndarray]  # (vertices (V, 3) float64, faces (F, 3) int64)
_Z = np.array([0.0, 0.0, 1.0])
OBJ_ROWS = 100_000  # vertices or faces formatted at a time


def empty() -> Mesh:
    return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh holding all of `meshes`."""
    meshes = [m for m in meshes if len(m[1])]
    if not meshes:
        return empty()
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    V = np.concatenate([v for v, _ in meshes])
    F = np.concatenate([f + o for (_, f), o in zip(meshes, offsets, strict=True)])
    return V, F.astype(np.int64)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def _segment_normals(d: np.ndarray) -> np.ndarray:
    """One normal per segment direction d (M, 3), each the previous one carried over without
    twist (rotation-minimising; a loop over the polyline's segments)."""
    n = np.empty_like(d)
    helper = _Z if abs(d[0] @ _Z) < 0.9 else np.array([1.0, 0.0, 0.0])
    n[0] = _unit(np.cross(d[0], helper))
    for j in range(1, len(d)):
        x = n[j - 1] - (n[j - 1] @ d[j]) * d[j]
        n[j] = _unit(x) if np.linalg.norm(x) > 1e-9 else n[j - 1]
    return n


def tube(polyline: np.ndarray, radius: float, segments: int = 12, caps: bool = True) -> Mesh:
    """A circle of `radius` swept along `polyline` (K, 3): a pipe. The ring at a joint is the
    incoming straight tube cut by the bisector plane (a mitre), so the tube keeps its radius
    through bends; `caps` closes both ends."""
    P = np.asarray(polyline, dtype=np.float64).reshape(-1, 3)
    P = P[np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-9]]
    if len(P) < 2 or radius <= 0.0:
        return empty()
    d = _unit(np.diff(P, axis=0))
    n = _segment_normals(d)
    b = np.cross(d, n)
    j = np.r_[0, np.arange(len(d))]  # the segment arriving at each vertex
    theta = 2.0 * np.pi * np.arange(segments) / segments
    q = radius * (np.cos(theta)[None, :, None] * n[j][:, None, :]
                  + np.sin(theta)[None, :, None] * b[j][:, None, :])  # fmt: skip
    t = np.concatenate([d[:1], _unit(d[:-1] + d[1:]), d[-1:]]) if len(d) > 1 else d[[0, 0]]
    dj = d[j]
    cosang = np.maximum(np.einsum("kc,kc->k", dj, t), 0.2)
    q = q - (np.einsum("ksc,kc->ks", q, t) / cosang[:, None])[..., None] * dj[:, None, :]
    K, S = len(P), segments
    V = (P[:, None, :] + q).reshape(-1, 3)
    F = grid_faces(K, S, wrap=True)
    if caps:
        F = np.concatenate([F, cap_faces(K, S)])
        V = np.concatenate([V, P[:1], P[-1:]])
    return V, F.astype(np.int64)


def cylinder(p0: np.ndarray, p1: np.ndarray, radius: float, segments: int = 16) -> Mesh:
    """Closed cylinder from p0 to p1 (a pole)."""
    return tube(np.stack([np.asarray(p0, float), np.asarray(p1, float)]), radius, segments)


def sweep_section(
    section: np.ndarray,
    path: np.ndarray,
    across: np.ndarray,
    up: np.ndarray,
    double_sided: bool = True,
) -> Mesh:
    """An open section curve (S, 2) as (u, v) swept along `path` (K, 3): vertex (k, i) =
    path[k] + u_i across[k] + v_i up[k] (a beam; `across` and `up` are per path vertex). A
    plate has no thickness here, so by default every face appears with both windings."""
    sec = np.asarray(section, dtype=np.float64).reshape(-1, 2)
    P = np.asarray(path, dtype=np.float64).reshape(-1, 3)
    if len(sec) < 2 or len(P) < 2:
        return empty()
    V = (P[:, None, :] + sec[None, :, 0, None] * across[:, None, :]
         + sec[None, :, 1, None] * up[:, None, :]).reshape(-1, 3)  # fmt: skip
    F = grid_faces(len(P), len(sec), wrap=False)
    if double_sided:
        F = np.concatenate([F, F[:, ::-1]])
    return V, F.astype(np.int64)


# ----------------------------------------------------------------------------- export


def _atomic_write(path: Path, data: bytes | str | Iterable[str]) -> None:
    """`data` (bytes, a string, or strings written one after another) as `path`."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        if isinstance(data, bytes | str):
            tmp.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
        else:
            with tmp.open("w", encoding="utf-8") as handle:
                handle.writelines(data)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _obj_lines(V: np.ndarray, F: np.ndarray, rows: int) -> Iterator[str]:
    """The mesh as OBJ text, `rows` vertices or faces at a time: a guardrail kilometres long
    has millions of them, and trimesh's export formats the whole file as one string (2 GB
    of memory on a simulated 4 km survey)."""
    yield "# mmsclean guardrail (world coordinates)\n"
    for start in range(0, len(V), rows):
        block = array_to_string(V[start : start + rows], col_delim=" ", row_delim="\nv ", digits=8)
        yield f"v {block}\n"
    for start in range(0, len(F), rows):
        block = array_to_string(F[start : start + rows] + 1, col_delim=" ", row_delim="\nf ")
        yield f"f {block}\n"


def export_mesh(
    mesh: Mesh, out_dir: str | Path, name: str, origin: np.ndarray | None = None
) -> dict[str, str]:
    """Write `mesh` (world coordinates) as OUT_DIR/NAME.glb, .obj and .ply (see module doc for
    `origin`, by default the centre of the vertices' bounding box); returns {format: path}."""
    V, F = mesh
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    V = np.asarray(V, dtype=np.float64)
    if origin is None:
        origin = 0.5 * (V.min(0) + V.max(0)) if len(V) else np.zeros(3)
    origin = np.asarray(origin, dtype=np.float64)
    local = trimesh.Trimesh(V - origin, np.asarray(F), process=False)
    T = np.eye(4)
    T[:3, 3] = origin
    scene = trimesh.Scene()
    scene.add_geometry(local, node_name=name, geom_name=name, transform=T)
    ply = local.export(file_type="ply")
    stamp = b"comment https://github.com/mikedh/trimesh\n"
    note = (
        f"comment origin {float(origin[0])!r} {float(origin[1])!r} {float(origin[2])!r}\n".encode()
    )
    ply = ply.replace(stamp, stamp + note, 1) if stamp in ply else ply
    files = {
        "glb": (out / f"{name}.glb", scene.export(file_type="glb")),
        "obj": (out / f"{name}.obj", _obj_lines(V, np.asarray(F, dtype=np.int64), OBJ_ROWS)),
        "ply": (out / f"{name}.ply", ply),
    }
    for path, data in files.values():
        _atomic_write(path, data)
    return {k: str(p) for k, (p, _) in files.items()}
