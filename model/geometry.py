"""Point geometry of the paper (section 3.1), vectorised: kNN, PCA frames, curvature, mean curvature, roughness.

One kNN query feeds every feature. Offsets and covariances are formed in float64 from the input
coordinates, so the features are the same for centred and uncentred (float64) scans; callers should
still centre tiles, since coordinates stored as float32 far from the origin have already lost precision.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np
from pykdtree.kdtree import KDTree

from model.rules import capped_twins, morton_order, most_twins

CHUNK_POINTS = 200_000  # points per batch of the metrics' queries (model/metrics.py, model/sdm.py)
QUERY_POINTS = 32_768  # points per kd-tree query: its float64 distances and indices are temporaries
FRAME_POINTS = 8_192  # rows per batch of (m, k) gathers, covariances and eigen solves (~15 (m, 3, 3) float64 temporaries): 32k cost 26 MB more at the same speed
# (at 200k a batch, a 200k-point tile's survey peaked at 295 MiB traced, and ran 12 % slower)
NEAR_DOUBLE = 1e-6  # |r| above 1 - this means a nearly repeated eigenvalue: LAPACK instead of the closed form
ROUND_OFF = 1e-12  # eigenvalues below this share of the trace are solver error (~1e-14 measured): exactly 0


@dataclass(frozen=True)
class Neighbours:
    """The k nearest neighbours of each point, nearest first, the point itself in column 0."""

    indices: np.ndarray  # (n, k) int64
    sq_dist: np.ndarray  # (n, k) float32 squared distances, ascending along a row, column 0 is 0

    @property
    def k(self) -> int:
        """Neighbours per point (the requested k, clipped to the point count)."""
        return self.indices.shape[1]


@dataclass(frozen=True)
class PointTree:
    """A kd-tree of (n, 3) float64 points for k-nearest queries, holding at most k points at any one position.

    pykdtree's search for 4 or more neighbours of one of c exact twins visits all c of them (50,000 twins:
    0.3 ms a query; a 2M-point scan whose no-return spot held 400,000 returns took minutes). A list of k
    nearest holds at most k twins of a position whatever the tree holds, so the distances listed are those
    of the whole cloud; which twin stands for a position may change (twins' features are the same), and
    where two positions tie at the k-th distance, which of them is listed (a smaller tree breaks ties its own
    way). Where no position has more than k twins the tree is the plain one, so such clouds' lists are
    unchanged (a hash sort checks it: 0.2 ms on a 22k-point tile, whose tree takes 2.8 ms).
    """

    tree: KDTree
    held: np.ndarray | None  # (m,) indices of the points the tree holds, ascending; None: every point
    k: int  # the most neighbours a query may ask for

    @classmethod
    def of(cls, xyz: np.ndarray, k: int, distinct: bool = False) -> PointTree:
        """The tree of `xyz` (n, 3) float64 for queries of up to `k` neighbours; `distinct`: the caller knows no
        two of the points share a position (a part of points it checked), so they are not checked again."""
        if distinct or most_twins(xyz) <= k:
            return cls(KDTree(xyz), None, k)
        held = capped_twins(xyz, k)
        return cls(KDTree(np.ascontiguousarray(xyz[held])), held, k)

    def query(self, points: np.ndarray, k: int, squared: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Distances (squared unless `squared` is False) and indices into the tree's points of the k nearest
        to each of (m, 3) float64 `points`, nearest first: (m, k) each, (m,) for k = 1."""
        if k > self.k:
            raise ValueError(f"{k} neighbours asked of a tree built for {self.k}")
        distance, index = self.tree.query(points, k, sqr_dists=squared)
        return distance, index if self.held is None else self.held[index]


def knn(xyz: np.ndarray, k: int = 16) -> Neighbours:
    """The k nearest neighbours of every point (k clipped to n), queried in chunks to bound memory.

    pykdtree, not scipy's cKDTree: 1.3-1.6x faster on one thread from 38k to 700k scan points, with
    the same distances (nanoflann and Open3D's search measured no faster on a 32k-point tile).
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    return neighbours(PointTree.of(xyz, k), xyz, np.arange(len(xyz)), k)


def neighbours(tree: PointTree, xyz: np.ndarray, rows: np.ndarray, k: int,
               order: np.ndarray | None = None) -> Neighbours:
    """The k nearest of the (n, 3) float64 points `tree` holds (`xyz`) to each of xyz[rows]: (len(rows), k).

    Queries go in Morton order (`order`, morton_order(xyz[rows]), if the caller has it) so consecutive
    ones walk the same nodes (700k shuffled points: 7.0 s in input order, 1.6 s with the sort). Among
    exact duplicates the tree may list a twin before the point itself, or not hold the point at all
    (PointTree); such rows are fixed so column 0 is always the point.
    """
    k = min(k, len(xyz))
    indices = np.empty((len(rows), k), dtype=np.int64)
    sq_dist = np.empty((len(rows), k), dtype=np.float32)
    if k == 0 or len(rows) == 0:
        return Neighbours(indices, sq_dist)
    order = morton_order(xyz[rows]) if order is None else order
    for start in range(0, len(rows), QUERY_POINTS):
        at = order[start : start + QUERY_POINTS]
        dist, idx = tree.query(xyz[rows[at]], k)
        indices[at] = idx.reshape(len(at), k)
        sq_dist[at] = dist.reshape(len(at), k)
    twins = np.flatnonzero(indices[:, 0] != rows)
    if len(twins):
        itself = rows[twins]
        listed = indices[twins]
        found = listed == itself[:, None]
        has = found.any(axis=1)  # else more than k twins: every column is a twin at distance 0
        listed[has, found[has].argmax(axis=1)] = listed[has, 0]
        listed[:, 0] = itself
        indices[twins] = listed
    return Neighbours(indices, sq_dist)


def nearest_member(xyz: np.ndarray, members: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """(q,) the position in `members` (m,) of the member nearest to each of xyz[queries] (both index the (n, 3)
    points xyz). A query that is a member is its own nearest, without a tree search: a search would return
    it or an exact twin among the members, and a thinning's values at twins are the same (their
    neighbourhoods list the same points), so only the other queries are searched: of the survey's two such
    searches on bcts's tiles, 60 % and 75 % of the queries."""
    slot = np.full(len(xyz), -1, dtype=np.int64)
    slot[members] = np.arange(len(members))
    found = slot[queries]
    rest = np.flatnonzero(found < 0)
    if len(rest):
        tree = PointTree.of(np.ascontiguousarray(xyz[members], dtype=np.float64), 1)
        _, index = tree.query(np.ascontiguousarray(xyz[queries[rest]], dtype=np.float64), 1)
        found[rest] = index
    return found


def local_frames(xyz: np.ndarray, nbrs: Neighbours,
                 rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (m, 3) float64 ascending and unit normals (m, 3) float32 of the covariance of each point
    xyz[rows] (every point when None) over its neighbours `nbrs` (m rows).

    As the paper writes it, C_i = sum_j (p_j - p_i)(p_j - p_i)^T over the neighbours j of i, centred on
    the point, not on the neighbourhood mean as in Pauly et al.'s surface variation (model/learning/losses.py
    mirrors this choice in torch; change both together). Measured on a sampled cube, the difference:
    about the point, edges and corners score alike (median kappa of points at exact edges 0.17, exact
    corners 0.14, faces 0) and a point's own offset from the surface adds to its kappa (plane with 1e-4
    noise: max 6e-5); about the mean, corners 0.15 > edges 0.08 > faces 0, noisy plane max 1.4e-5.
    The normal is the eigenvector of the smallest eigenvalue, sign arbitrary.
    """
    rows = np.arange(len(xyz)) if rows is None else rows
    eigenvalues = np.zeros((len(rows), 3))
    normals = np.zeros((len(rows), 3), dtype=np.float32)
    for batch, parts in _covariances(xyz, nbrs, rows):
        eigenvalues[batch], normals[batch] = _symmetric_eigen(parts)
    return eigenvalues, normals


def local_eigenvalues(xyz: np.ndarray, nbrs: Neighbours, rows: np.ndarray | None = None) -> np.ndarray:
    """local_frames' eigenvalues (m, 3) alone, the same values: the curvature features need no normals, and
    the eigenvectors cost more than the eigenvalues."""
    rows = np.arange(len(xyz)) if rows is None else rows
    eigenvalues = np.zeros((len(rows), 3))
    for batch, parts in _covariances(xyz, nbrs, rows):
        eigenvalues[batch] = _symmetric_eigenvalues(parts)
    return eigenvalues


def _covariances(xyz: np.ndarray, nbrs: Neighbours, rows: np.ndarray) -> Iterator[tuple[slice, np.ndarray]]:
    """Batches of FRAME_POINTS rows: (slice of rows, (6, m) float64 covariance entries xx, yy, zz, xy, xz,
    yz of each row over its neighbours, about the row's own point).

    Offsets d = p_j - p_i are formed in float64, so they stay small wherever the origin is, and the
    entries stay float64 (float32 LAPACK erred by ~5e-8 in kappa, ten times the whole kappa of a patch
    whose noise is 1e-4 of its extent). Each coordinate is gathered into its own (m, k) plane and the
    six entries summed over k: 2.4x faster than a batched (3, k) @ (k, 3) product, equal to it within
    1e-15 relative."""
    planes = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64).T)  # (3, n)
    buffer = np.empty((3, min(len(rows), FRAME_POINTS), nbrs.k))  # reused: fresh pages per batch cost more than the maths
    for start in range(0, len(rows), FRAME_POINTS):
        batch = slice(start, min(start + FRAME_POINTS, len(rows)))
        offsets = buffer[:, : batch.stop - start]
        for axis in range(3):
            np.take(planes[axis], nbrs.indices[batch], out=offsets[axis])  # faster than fancy indexing
            offsets[axis] -= planes[axis, rows[batch], None]
        x, y, z = offsets
        yield batch, np.stack([np.einsum("mk,mk->m", a, b) for a, b in ((x, x), (y, y), (z, z), (x, y), (x, z), (y, z))])


def _cubic_roots(parts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The trigonometric solution of the characteristic cubic of (6, m) symmetric 3x3 matrices (entries xx,
    yy, zz, xy, xz, yz), solved on trace-normalised matrices so any scale works: ascending eigenvalues
    (m, 3) of the normalised matrices, where they are reliable (`closed`: False where two nearly coincide,
    as arccos then loses precision: points on a line, isotropic blobs, duplicates), the normalised entries
    (6, m) and the trace (m,) they were divided by (1 where it is 0)."""
    trace = parts[0] + parts[1] + parts[2]
    scale = np.where(trace > 0, trace, 1.0)
    c = parts / scale
    q = (c[0] + c[1] + c[2]) / 3
    xx, yy, zz = c[0] - q, c[1] - q, c[2] - q
    xy, xz, yz = c[3], c[4], c[5]
    p = np.sqrt((xx * xx + yy * yy + zz * zz + 2 * (xy * xy + xz * xz + yz * yz)) / 6)
    det = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = det / (2 * p**3)
    closed = np.abs(r) < 1 - NEAR_DOUBLE  # False for NaN (p = 0) too
    phi = np.arccos(np.where(closed, r, 0)) / 3
    largest = q + 2 * p * np.cos(phi)
    smallest = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    return np.stack([smallest, 3 * q - smallest - largest, largest], axis=1), closed, c, scale


def _matrices(parts: np.ndarray) -> np.ndarray:
    """(m, 3, 3) symmetric matrices of (6, m) entries xx, yy, zz, xy, xz, yz."""
    xx, yy, zz, xy, xz, yz = parts
    return np.stack([np.stack([xx, xy, xz], axis=1), np.stack([xy, yy, yz], axis=1), np.stack([xz, yz, zz], axis=1)],
                    axis=1)


def _symmetric_eigenvalues(parts: np.ndarray) -> np.ndarray:
    """Ascending eigenvalues (m, 3) of (6, m) symmetric PSD matrices (see _symmetric_eigen)."""
    values, closed, c, scale = _cubic_roots(parts)
    if not closed.all():
        values[~closed] = np.linalg.eigh(_matrices(c[:, ~closed]))[0]
    values[values < ROUND_OFF] = 0
    return values * scale[:, None]


def _symmetric_eigen(parts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ascending eigenvalues and the smallest one's unit eigenvector of (6, m) symmetric PSD matrices
    (entries xx, yy, zz, xy, xz, yz).

    The closed form (_cubic_roots) matched LAPACK to ~1e-14 of the trace and ran 5x faster; the normal
    is the longest cross product of two rows of C - l0 I. Where two eigenvalues nearly coincide (the
    cross products vanish too) LAPACK's eigh is used. Eigenvalues below ROUND_OFF of the trace are set
    to 0, so exactly flat patches have kappa exactly 0 (ties, not round-off noise).
    """
    values, closed, c, scale = _cubic_roots(parts)
    rows = _matrices(c) - values[:, 0, None, None] * np.eye(3)
    crosses = np.cross(rows[:, [0, 0, 1]], rows[:, [1, 2, 2]])
    lengths = np.einsum("mij,mij->mi", crosses, crosses)
    best = lengths.argmax(axis=1)
    picked = np.arange(len(scale))
    vectors = crosses[picked, best] / np.sqrt(np.where(closed, lengths[picked, best], 1.0))[:, None]
    if not closed.all():
        values[~closed], frames = np.linalg.eigh(_matrices(c[:, ~closed]))
        vectors[~closed] = frames[:, :, 0]
    values[values < ROUND_OFF] = 0
    return values * scale[:, None], vectors


def curvature(eigenvalues: np.ndarray) -> np.ndarray:
    """kappa = l0 / (l0 + l1 + l2) (float32, in [0, 1/3]); 0 where the sum is 0 (all neighbours coincide)."""
    total = eigenvalues.sum(axis=1)
    return np.divide(eigenvalues[:, 0], total, out=np.zeros(len(total)), where=total > 0).astype(np.float32)


def bandwidth(nbrs: Neighbours) -> np.ndarray:
    """Per-point Gaussian bandwidth h_i: the squared distance to i's (k/2)-th nearest neighbour.

    The paper's h is one constant; a per-point h tied to the local spacing keeps the weights the same
    shape at any scale (scale-invariant mean curvature) and at any density (LiDAR density varies a
    hundredfold with range, and one constant per tile would make features depend on the tiling). The
    median neighbour's distance rather than the mean ignores a few far neighbours, and the kNN rows
    are sorted, so it costs nothing. Where half the neighbours coincide with the point, h is inf
    (uniform weights).
    """
    h = nbrs.sq_dist[:, nbrs.k // 2].copy() if nbrs.k else np.zeros(0, dtype=np.float32)
    h[h == 0] = np.inf
    return h


def mean_curvature(kappa: np.ndarray, nbrs: Neighbours, h: np.ndarray | float) -> np.ndarray:
    """K_i = sum_j kappa_j w_ij / sum_j w_ij, w_ij = exp(-d_ij^2 / h_i), over i's neighbours (itself included):
    one value per row of `nbrs` (kappa is indexed by their indices).

    `h` is per row (see `bandwidth`) or one constant as in the paper; the point's own weight is 1,
    so the denominator never vanishes.
    """
    h = np.broadcast_to(np.asarray(h, dtype=np.float32), (len(nbrs.indices),))
    kbar = np.empty(len(nbrs.indices), dtype=np.float32)
    for start in range(0, len(kbar), FRAME_POINTS):  # (m, k) temporaries a batch at a time
        rows = slice(start, start + FRAME_POINTS)
        weights = np.exp(-nbrs.sq_dist[rows] / h[rows, None])
        kbar[rows] = np.einsum("nk,nk->n", kappa[nbrs.indices[rows]], weights) / weights.sum(axis=1)
    return kbar


def roughness(kappa: np.ndarray, kbar: np.ndarray) -> np.ndarray:
    """R_i = |kappa_i - K_i|: how much a point's curvature departs from its neighbourhood's."""
    return np.abs(kappa - kbar)


@dataclass(frozen=True)
class PointFeatures:
    """Every per-point feature of section 3.1, from one kNN query."""

    nbrs: Neighbours
    normals: np.ndarray  # (n, 3) float32 unit, sign arbitrary
    kappa: np.ndarray  # (n,) float32
    mean_curvature: np.ndarray  # (n,) float32
    roughness: np.ndarray  # (n,) float32


def point_features(xyz: np.ndarray, k: int = 16) -> PointFeatures:
    """Normals, curvature, mean curvature (per-point bandwidth) and roughness of every point."""
    nbrs = knn(xyz, k)
    eigenvalues, normals = local_frames(xyz, nbrs)
    kappa = curvature(eigenvalues)
    kbar = mean_curvature(kappa, nbrs, bandwidth(nbrs))
    return PointFeatures(nbrs, normals, kappa, kbar, roughness(kappa, kbar))


@dataclass(frozen=True)
class LocalFeatures:
    """Curvature features of some rows of a cloud, their neighbours found among all its points."""

    nbrs: Neighbours  # (m, k) the rows' neighbours, indices into the whole cloud
    eigenvalues: np.ndarray  # (m, 3) float64 ascending
    kappa: np.ndarray  # (n,) float32: set on the rows, their neighbours and the neighbours' neighbours, else 0
    mean_curvature: np.ndarray  # (n,) float32: set on the rows and their neighbours, else 0


def local_features(xyz: np.ndarray, rows: np.ndarray, k: int = 16, order: np.ndarray | None = None,
                   tree: PointTree | None = None) -> LocalFeatures:
    """Features of xyz[rows] as point_features gives them on the whole cloud, querying only the rows and the
    two rings of neighbours their mean curvature and its spread reach: a tile's halo is there as
    neighbours, and most of a fixed-width halo lies beyond those rings on a dense scan. `order`:
    a good query order of the rows (morton_order(xyz[rows])), if the caller has one; `tree`: PointTree.of(xyz,
    k), if the caller has one."""
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    if len(rows) == 0:
        empty = Neighbours(np.empty((0, min(k, len(xyz))), dtype=np.int64), np.empty((0, min(k, len(xyz))), np.float32))
        return LocalFeatures(empty, np.empty((0, 3)), np.zeros(len(xyz), np.float32), np.zeros(len(xyz), np.float32))
    tree = PointTree.of(xyz, k) if tree is None else tree
    queried = np.zeros(len(xyz), dtype=bool)
    kappa = np.zeros(len(xyz), dtype=np.float32)
    found: list[tuple[np.ndarray, Neighbours]] = []  # the rows and the first ring, with their neighbours
    wanted = np.asarray(rows, dtype=np.int64)
    for ring in range(3):  # the rows, their neighbours, the neighbours' neighbours (kappa only)
        if ring:
            reached = np.zeros(len(xyz), dtype=bool)
            reached[found[-1][1].indices.ravel()] = True  # a scatter, not np.unique's sort of m * k indices
            wanted = np.flatnonzero(reached & ~queried)
        ring_nbrs = neighbours(tree, xyz, wanted, k, None if ring else order)
        queried[wanted] = True
        eigenvalues = local_eigenvalues(xyz, ring_nbrs, wanted)
        kappa[wanted] = curvature(eigenvalues)
        if ring == 0:
            row_eigenvalues = eigenvalues
        if ring < 2:
            found.append((wanted, ring_nbrs))
    kbar = np.zeros(len(xyz), dtype=np.float32)
    for wanted, ring_nbrs in found:
        kbar[wanted] = mean_curvature(kappa, ring_nbrs, bandwidth(ring_nbrs))
    return LocalFeatures(found[0][1], row_eigenvalues, kappa, kbar)


DISTANCE_QUANTILES = np.linspace(0.0, 1.0, 65)  # a tile reports a distribution of distances as these quantiles


def nearest_distance(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Distance from each query to the nearest of `points` (both (m, 3))."""
    tree = PointTree.of(np.ascontiguousarray(points, dtype=np.float64), 1)
    distance, _ = tree.query(np.ascontiguousarray(queries, dtype=np.float64), 1, squared=False)
    return distance
