"""Ray casting against a `Scene`: static geometry in one BVH, moving bodies in their own frames.

Static bodies (mesh already in world coordinates) share one open3d `RaycastingScene`. Every
moving body gets its own scene of its mesh in its LOCAL frame (as does a static body with a halo,
e.g. a parked car, in a frame at its centre); a ray is taken into that frame at
the ray's OWN time (`Motion.world_to_local(times)`), so a body that moves while a scanner sweeps
over it is hit at a different place by every ray: the smeared "phantom" of the phantom paper
(Nagy & Benedek) comes out of the geometry, nothing is faked afterwards.

Car bodies with `halo_margin > 0` also get a "halo" scene: the mesh inflated by the margin. A ray
that grazes the halo but misses the body itself becomes, with probability `halo_probability`, a
return on that body at the halo distance (flagged `halo`): the enlarged shape of cars caused by
laser bounce and transmission through glass (clutter paper, Lee et al. 2020, section 2.2.3).
Cameras cast with `with_halo=False`: the halo is a LiDAR artefact.

Precision: world coordinates stay float64 in numpy; open3d casts in float32. Static vertices and
ray origins are re-centred on the middle of the static geometry before the float32 cast, and
moving bodies are cast in their local frames, so float32 rounding is relative to the scene's
extent: ~0.06 mm spacing at 1 km, ~0.5 mm at 5 km, and ranges (float32 `t_hit`) carry a relative
error of ~1e-7 (0.02 mm at 200 m). Hit points are rebuilt in float64 as origin + distance * dir.

Culling of moving bodies costs almost nothing per ray: rays are grouped in blocks of
`BLOCK` consecutive rays (scanner patterns are time ordered, so a block spans a short time and a
narrow cone of directions); a block is kept for a body only if its cone of rays can meet the
body's bounding sphere (radius + halo margin, grown by the distance the body can travel within
the block's time span) within `max_range`. Rays of kept blocks get the exact per-ray test at their
own time (and are dropped when an already found hit is nearer than the sphere).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from app.simulate.scene import Body, Mesh, Motion, Scene

BLOCK = 256  # rays per culling block
INVALID = np.uint32(0xFFFFFFFF)  # open3d's id for "no hit"


@dataclass
class Hits:
    """What each ray hit. Misses: distance inf, body -1, triangle -1, normal 0."""

    distance: np.ndarray  # (N,) float64, np.inf = no hit
    body: np.ndarray  # (N,) int32 index into scene.bodies, -1 = miss
    triangle: np.ndarray  # (N,) int64 triangle of that body's mesh, -1 = miss
    normal: np.ndarray  # (N, 3) float64 world, unit, facing the ray (dot(normal, dir) <= 0)
    halo: np.ndarray  # (N,) bool: a laser-bounce return off the body's halo, not its surface

    @property
    def hit(self) -> np.ndarray:
        return self.body >= 0

    def __len__(self) -> int:
        return len(self.distance)

    @classmethod
    def misses(cls, n: int) -> Hits:
        """n rays that hit nothing (yet)."""
        return cls(
            distance=np.full(n, np.inf),
            body=np.full(n, -1, dtype=np.int32),
            triangle=np.full(n, -1, dtype=np.int64),
            normal=np.zeros((n, 3)),
            halo=np.zeros(n, dtype=bool),
        )

    def face(self, directions: np.ndarray) -> Hits:
        """Turn every normal towards its ray (dot(normal, direction) <= 0)."""
        facing = np.einsum("ij,ij->i", self.normal, directions)
        self.normal *= np.where(facing > 0, -1.0, 1.0)[:, None]
        return self


def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals (T, 3) of triangles wound counter-clockwise (zero for degenerate ones)."""
    v = vertices[triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def inflate(mesh: Mesh, margin: float) -> Mesh:
    """The mesh with every vertex moved `margin` outwards along its averaged vertex normal.

    Vertices at the same position are welded first (so boxes built from separate faces inflate
    without cracks), and each face normal is turned away from the mesh centroid, so the result
    does not depend on winding. Every point of the inflated surface lies within `margin` of the
    original surface (a convex combination of unit offsets is at most one margin long).
    """
    V, F = mesh.vertices, mesh.triangles
    if not len(F) or margin <= 0:
        return Mesh(V.copy(), F.copy(), mesh.part.copy())
    n = face_normals(V, F)
    centre = V.mean(axis=0)
    outward = np.einsum("ij,ij->i", n, V[F].mean(axis=1) - centre) >= 0
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    n = np.where(outward[:, None], n, -n) * area[:, None]
    scale = max(float(np.ptp(V, axis=0).max()), 1e-9)
    _, weld = np.unique(np.round(V / (scale * 1e-6)).astype(np.int64), axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    acc = np.zeros((weld.max() + 1, 3))
    np.add.at(acc, weld[F.reshape(-1)], np.repeat(n, 3, axis=0))
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    vn = np.divide(acc, length, out=np.zeros_like(acc), where=length > 0)[weld]
    return Mesh(V + margin * vn, F.copy(), mesh.part.copy())


def _scene_of(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )
    return scene


def _cast(
    scene: o3d.t.geometry.RaycastingScene,
    origins: np.ndarray,
    directions: np.ndarray,
    max_range: float,
    threads: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Distance (float64, inf beyond max_range / miss) and primitive id (int64, -1 miss)."""
    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = directions
    out = scene.cast_rays(o3d.core.Tensor(rays), nthreads=threads)
    t = out["t_hit"].numpy().astype(np.float64)
    prim = out["primitive_ids"].numpy()
    miss = (prim == INVALID) | ~(t <= max_range)
    t[miss] = np.inf
    prim = prim.astype(np.int64)
    prim[miss] = -1
    return t, prim


@dataclass
class _Static:
    """The merged static bodies: one open3d scene and per-triangle lookups back to bodies."""

    scene: o3d.t.geometry.RaycastingScene
    origin: np.ndarray  # subtracted before float32 casting
    tri_body: np.ndarray  # (T,) body index of each merged triangle
    tri_local: np.ndarray  # (T,) triangle index within its body's mesh
    tri_normal: np.ndarray  # (T, 3) world face normals
    triangles: int


class _SceneCache:
    """The open3d scenes of bodies cast in their own frames, built when first needed and at
    most `size` alive: every RaycastingScene holds an Embree device of its own, and a process
    dies (segfault in open3d) after one to two thousand of them, fewer than the moving and
    parked cars of a 4 km street. Rays come in time order, so the bodies near the scanner
    stay in the cache."""

    def __init__(self, size: int = 256):
        self.size = size
        self._scenes: OrderedDict[tuple[int, str], o3d.t.geometry.RaycastingScene] = OrderedDict()

    def get(self, key: tuple[int, str], mesh: Mesh) -> o3d.t.geometry.RaycastingScene:
        scene = self._scenes.pop(key, None)
        if scene is None:
            scene = _scene_of(mesh.vertices, mesh.triangles)
        self._scenes[key] = scene
        if len(self._scenes) > self.size:
            self._scenes.popitem(last=False)
        return scene


@dataclass
class _Moving:
    index: int  # body index
    motion: Motion  # a constant one for static bodies with a halo
    radius: float  # bounding radius + halo margin
    speed: float  # max speed along the sampled path (m/s)
    mesh: Mesh  # in the body's frame
    normals: np.ndarray  # (T, 3) local face normals
    halo_mesh: Mesh | None
    halo_normals: np.ndarray | None
    scenes: _SceneCache

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        return self.scenes.get((self.index, "body"), self.mesh)

    @property
    def halo_scene(self) -> o3d.t.geometry.RaycastingScene | None:
        if self.halo_mesh is None:
            return None
        return self.scenes.get((self.index, "halo"), self.halo_mesh)


class RayCaster:
    """Casts rays (world, float64) at given times against every body of a scene."""

    def __init__(
        self,
        scene: Scene,
        halo_probability: float = 0.5,
        chunk_size: int = 1_000_000,
        threads: int = 0,
    ) -> None:
        if not 0.0 <= halo_probability <= 1.0:
            raise ValueError(f"halo_probability must be in [0, 1], got {halo_probability}")
        self.scene = scene
        self.halo_probability = float(halo_probability)
        self.chunk_size = int(chunk_size)
        self.threads = int(threads)  # open3d threads, 0 = all cores
        self._scenes = _SceneCache()
        self._static_lidar = self._build_static(scene.bodies, with_halo_bodies=False)
        own = [i for i, b in enumerate(scene.bodies) if b.moving or b.halo_margin > 0]
        built = (self._build_moving(i, scene.bodies[i]) for i in own)
        self.moving = [m for m in built if m is not None]  # own-frame bodies (moving or halo)
        self._moving_only = [m for m in self.moving if scene.bodies[m.index].moving]
        if len(self._moving_only) == len(self.moving):
            self._static_camera = self._static_lidar
        else:
            self._static_camera = self._build_static(scene.bodies, with_halo_bodies=True)
        self.static_triangles = 0 if self._static_lidar is None else self._static_lidar.triangles

    # -- construction -------------------------------------------------------------------------

    def _build_static(self, bodies: list[Body], with_halo_bodies: bool) -> _Static | None:
        """One scene of the static bodies; static bodies with a halo (parked cars) are left out
        for LiDAR casts, which treat them in their own frame, and put in for camera casts."""
        static = [
            i
            for i, b in enumerate(bodies)
            if not b.moving and (with_halo_bodies or b.halo_margin <= 0) and len(b.mesh.triangles)
        ]
        if not static:
            return None
        meshes = [bodies[i].mesh for i in static]
        merged = Mesh.merge(meshes)
        lo, hi = merged.vertices.min(axis=0), merged.vertices.max(axis=0)
        origin = 0.5 * (lo + hi)  # float32 work is relative to the middle of the scene
        counts = np.array([len(m.triangles) for m in meshes])
        starts = np.cumsum(counts) - counts
        return _Static(
            scene=_scene_of(merged.vertices - origin, merged.triangles),
            origin=origin,
            tri_body=np.repeat(np.asarray(static, dtype=np.int32), counts),
            tri_local=np.arange(len(merged.triangles), dtype=np.int64) - np.repeat(starts, counts),
            tri_normal=face_normals(merged.vertices, merged.triangles),
            triangles=len(merged.triangles),
        )

    def _build_moving(self, index: int, body: Body) -> _Moving | None:
        mesh = body.mesh
        if not len(mesh.triangles):
            return None
        motion = body.motion
        if motion is None:  # a static body with a halo (parked car): cast in a frame at its centre
            centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
            mesh = Mesh(mesh.vertices - centre, mesh.triangles, mesh.part)
            motion = Motion(np.zeros(1), centre[None, :], np.zeros(1))
        margin = max(float(body.halo_margin), 0.0)
        if len(motion.times) > 1:
            step = np.linalg.norm(np.diff(motion.positions, axis=0), axis=1)
            dt = np.maximum(np.diff(motion.times), 1e-12)
            speed = float((step / dt).max())
        else:
            speed = 0.0
        halo = halo_normals = None
        if margin > 0:
            halo = inflate(mesh, margin)
            halo_normals = face_normals(halo.vertices, halo.triangles)
        return _Moving(
            index=index,
            motion=motion,
            radius=mesh.bounding_radius() + margin,
            speed=speed,
            mesh=mesh,
            normals=face_normals(mesh.vertices, mesh.triangles),
            halo_mesh=halo,
            halo_normals=halo_normals,
            scenes=self._scenes,
        )

    # -- casting ------------------------------------------------------------------------------

    def cast(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        times: np.ndarray | float,
        max_range: float,
        rng: np.random.Generator | None = None,
        with_halo: bool = True,
    ) -> Hits:
        """Nearest hit of each ray within `max_range`, moving bodies placed at each ray's time.

        `directions` must be unit vectors. `rng` draws the halo returns; it may be None only when
        no halo can occur (`with_halo=False`, no halo bodies or `halo_probability` 0).
        """
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        n = len(origins)
        if len(directions) != n:
            raise ValueError("origins and directions need the same number of rays")
        times = np.broadcast_to(np.asarray(times, dtype=np.float64), (n,))
        hits = Hits.misses(n)
        for a in range(0, n, self.chunk_size):
            b = min(a + self.chunk_size, n)
            self._cast_chunk(
                origins[a:b], directions[a:b], times[a:b], max_range, rng, with_halo, hits, a
            )
        return hits.face(directions)

    def _cast_static(
        self,
        static: _Static | None,
        o: np.ndarray,
        d: np.ndarray,
        max_range: float,
        hits: Hits,
        sl: slice,
    ) -> None:
        """Fill hits[sl] with the nearest static hits (first pass, so no comparison needed)."""
        if static is None:
            return
        dist, prim = _cast(static.scene, o - static.origin, d, max_range, self.threads)
        ok = prim >= 0
        p = np.where(ok, prim, 0)
        hits.distance[sl] = dist
        hits.body[sl] = np.where(ok, np.take(static.tri_body, p), -1)
        hits.triangle[sl] = np.where(ok, np.take(static.tri_local, p), -1)
        hits.normal[sl] = np.take(static.tri_normal, p, axis=0) * ok[:, None]

    def cast_from(
        self, origin: np.ndarray, directions: np.ndarray, time: float, max_range: float
    ) -> Hits:
        """Rays from one point at one instant (a camera), without halo.

        Each moving body is placed once at `time` and culled with one cone test against its
        bounding sphere, much cheaper than the per-ray-time path of `cast`.
        """
        origin = np.asarray(origin, dtype=np.float64).reshape(3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        n = len(d)
        hits = Hits.misses(n)
        o = np.broadcast_to(origin, d.shape)
        self._cast_static(self._static_camera, o, d, max_range, hits, slice(0, n))
        for m in self._moving_only:
            T = m.motion.poses(np.array([time]))[0]
            w = T[:3, 3] - origin
            centre_distance = float(np.linalg.norm(w))
            if centre_distance - m.radius > max_range:
                continue
            if centre_distance > m.radius:
                cone = np.sqrt(1.0 - (m.radius / centre_distance) ** 2)
                cand = np.flatnonzero(d @ (w / centre_distance) >= cone)
            else:
                cand = np.arange(n)
            cand = cand[hits.distance[cand] > centre_distance - m.radius]
            if not len(cand):
                continue
            R = T[:3, :3]
            o_l = np.broadcast_to(R.T @ (origin - T[:3, 3]), (len(cand), 3))
            dist, prim = _cast(m.scene, o_l, d[cand] @ R, max_range, self.threads)
            near = dist < hits.distance[cand]
            j = cand[near]
            hits.distance[j] = dist[near]
            hits.body[j] = m.index
            hits.triangle[j] = prim[near]
            hits.normal[j] = np.take(m.normals, prim[near], axis=0) @ R.T
        return hits.face(d)

    def _cast_chunk(
        self,
        o: np.ndarray,
        d: np.ndarray,
        t: np.ndarray,
        max_range: float,
        rng: np.random.Generator | None,
        with_halo: bool,
        hits: Hits,
        offset: int,
    ) -> None:
        sl = slice(offset, offset + len(o))
        best, body, tri = hits.distance[sl], hits.body[sl], hits.triangle[sl]
        normal, halo = hits.normal[sl], hits.halo[sl]
        self._cast_static(
            self._static_lidar if with_halo else self._static_camera, o, d, max_range, hits, sl
        )
        movers = self.moving if with_halo else self._moving_only
        if not movers:
            return
        blocks = _Blocks(o, d, t)
        for m in movers:
            idx = self._candidates(m, blocks, o, d, t, best, max_range)
            if not len(idx):
                continue
            Rt, tl = m.motion.world_to_local(t[idx])
            o_l = np.einsum("nij,nj->ni", Rt, o[idx]) + tl
            d_l = np.einsum("nij,nj->ni", Rt, d[idx])
            dist, prim = _cast(m.scene, o_l, d_l, max_range, self.threads)
            near = dist < best[idx]
            if near.any():
                j = idx[near]
                best[j] = dist[near]
                body[j] = m.index
                tri[j] = prim[near]
                halo[j] = False
                normal[j] = np.einsum(
                    "nji,nj->ni", Rt[near], np.take(m.normals, prim[near], axis=0)
                )
            if not with_halo or m.halo_mesh is None or self.halo_probability <= 0:
                continue
            miss = ~np.isfinite(dist)
            if not miss.any():
                continue
            h_dist, h_prim = _cast(m.halo_scene, o_l[miss], d_l[miss], max_range, self.threads)
            k = np.flatnonzero(miss)
            cand = h_dist < best[idx[k]]
            if not cand.any():
                continue
            if rng is None:
                raise ValueError("RayCaster.cast needs an rng when halo returns can occur")
            k, h_dist, h_prim = k[cand], h_dist[cand], h_prim[cand]
            take = rng.random(len(k)) < self.halo_probability
            k, h_dist, h_prim = k[take], h_dist[take], h_prim[take]
            j = idx[k]
            best[j] = h_dist
            body[j] = m.index
            tri[j] = h_prim
            halo[j] = True
            normal[j] = np.einsum("nji,nj->ni", Rt[k], np.take(m.halo_normals, h_prim, axis=0))

    @staticmethod
    def _candidates(
        m: _Moving,
        blocks: _Blocks,
        o: np.ndarray,
        d: np.ndarray,
        t: np.ndarray,
        best: np.ndarray,
        max_range: float,
    ) -> np.ndarray:
        """Indices of rays that can hit body `m` (sphere test at each ray's own time)."""
        keep = blocks.may_meet(m.motion, m.radius, m.speed, max_range)
        if not keep.any():
            return np.zeros(0, dtype=np.int64)
        idx = blocks.rays_of(keep)
        c = m.motion.position(t[idx])
        w = c - o[idx]
        dw = np.linalg.norm(w, axis=1)
        s = np.einsum("ij,ij->i", w, d[idx])
        perp2 = np.maximum(dw * dw - s * s, 0.0)
        r = m.radius
        nearest = np.maximum(dw - r, 0.0)  # no point of the sphere is nearer than this
        inside = dw <= r
        ok = (inside | ((s > 0) & (perp2 <= r * r))) & (nearest <= max_range)
        ok &= nearest < best[idx]
        return idx[ok]


class _Blocks:
    """Consecutive rays grouped by BLOCK: time span, origin ball and direction cone per block."""

    def __init__(self, o: np.ndarray, d: np.ndarray, t: np.ndarray) -> None:
        n = len(o)
        self.n = n
        nb = -(-n // BLOCK)
        pad = nb * BLOCK - n

        def blocked(x: np.ndarray) -> np.ndarray:
            if pad:
                x = np.concatenate([x, np.repeat(x[-1:], pad, axis=0)])
            return x.reshape(nb, BLOCK, *x.shape[1:])

        tb, ob, db = blocked(t), blocked(o), blocked(d)
        self.t_lo, self.t_hi = tb.min(axis=1), tb.max(axis=1)
        lo, hi = ob.min(axis=1), ob.max(axis=1)
        self.centre = 0.5 * (lo + hi)
        self.spread = 0.5 * np.linalg.norm(hi - lo, axis=1)
        axis = db.sum(axis=1)
        length = np.linalg.norm(axis, axis=1, keepdims=True)
        axis = np.divide(axis, length, out=np.zeros_like(axis), where=length > 1e-9)
        cos_half = np.einsum("bkj,bj->bk", db, axis).min(axis=1)
        cos_half[length[:, 0] <= 1e-9] = -1.0
        self.axis = axis
        self.half_angle = np.arccos(np.clip(cos_half, -1.0, 1.0))

    def may_meet(self, motion: Motion, radius: float, speed: float, max_range: float) -> np.ndarray:
        """Blocks whose rays can meet the body's bounding sphere at some time of the block."""
        c = motion.position(0.5 * (self.t_lo + self.t_hi))
        R = radius + speed * 0.5 * (self.t_hi - self.t_lo) + self.spread
        w = c - self.centre
        dist = np.linalg.norm(w, axis=1)
        cos_w = np.einsum("ij,ij->i", w, self.axis) / np.maximum(dist, 1e-12)
        angle = np.arccos(np.clip(cos_w, -1.0, 1.0))
        allowed = self.half_angle + np.arcsin(np.clip(R / np.maximum(dist, 1e-12), 0.0, 1.0))
        return (dist <= R) | ((angle <= allowed) & (dist - R <= max_range))

    def rays_of(self, keep: np.ndarray) -> np.ndarray:
        idx = (np.flatnonzero(keep)[:, None] * BLOCK + np.arange(BLOCK)).reshape(-1)
        return idx[idx < self.n]
