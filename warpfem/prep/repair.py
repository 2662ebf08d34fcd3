"""Surface repairs beyond welding: closing small holes and finding shells (connected components).

Holes are boundary loops. A loop is closed when it is *small*: its bounding box spans at most
``MAX_HOLE_FRACTION`` of the mesh's bounding-box diagonal (stanford-bunny.obj's five holes in its base
span 0.05 to 0.18). The loop is projected onto its least-squares plane and triangulated by ear
clipping (a flat cap, no new vertices); if the projected polygon is not simple, a fan around the loop's
centroid (one new vertex) is used instead. Caps are wound opposite to the faces around the hole, so the
surface stays consistently wound.
"""

from __future__ import annotations

import numpy as np

MAX_HOLE_FRACTION = 0.25
"""Largest hole closed automatically: its loop's bounding-box diagonal / the mesh's bounding-box diagonal."""


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Return the boundary loops of an edge-manifold triangle mesh, each in the faces' edge direction.

    Args:
        faces: (m, 3) vertex indices.

    Returns:
        One int64 array of vertex indices per loop, ordered so that (loop[k], loop[k+1]) is a directed
        edge of a face.

    Raises:
        ValueError: If a boundary vertex has more than one outgoing boundary edge (a pinched boundary).
    """
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.reshape(-1)] == 1]
    if len(boundary) == 0:
        return []
    nxt: dict[int, int] = {}
    for a, b in boundary.tolist():
        if a in nxt:
            raise ValueError(f"boundary is pinched at vertex {a}")
        nxt[a] = b
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt.get(v, start)
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def _signed_area_2d(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _segments_cross(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> bool:
    def side(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    return side(p1, p2, q1) * side(p1, p2, q2) < 0 and side(q1, q2, p1) * side(q1, q2, p2) < 0


def _is_simple(poly: np.ndarray) -> bool:
    n = len(poly)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            if _segments_cross(poly[i], poly[(i + 1) % n], poly[j], poly[(j + 1) % n]):
                return False
    return True


def ear_clip(poly: np.ndarray) -> np.ndarray | None:
    """Triangulate a simple counter-clockwise 2D polygon by ear clipping.

    Args:
        poly: (k, 2) corners, counter-clockwise.

    Returns:
        (k-2, 3) int64 corner indices, counter-clockwise, or None if no ear is found (not simple).
    """
    remaining = list(range(len(poly)))
    triangles = []
    while len(remaining) > 3:
        for k in range(len(remaining)):
            i, j, m = remaining[k - 1], remaining[k], remaining[(k + 1) % len(remaining)]
            a, b, c = poly[i], poly[j], poly[m]
            if (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) <= 0:
                continue  # reflex or flat corner
            others = [poly[r] for r in remaining if r not in (i, j, m)]
            if any(_in_triangle(p, a, b, c) for p in others):
                continue
            triangles.append((i, j, m))
            remaining.pop(k)
            break
        else:
            return None
    triangles.append(tuple(remaining))
    return np.array(triangles, dtype=np.int64)


def _in_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
    d1 = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    d2 = (c[0] - b[0]) * (p[1] - b[1]) - (c[1] - b[1]) * (p[0] - b[0])
    d3 = (a[0] - c[0]) * (p[1] - c[1]) - (a[1] - c[1]) * (p[0] - c[0])
    return d1 >= 0 and d2 >= 0 and d3 >= 0


def cap_loop(vertices: np.ndarray, loop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate one hole so that its triangles traverse the loop's edges in the opposite direction.

    Args:
        vertices: (n, 3) positions.
        loop: (k,) boundary vertex indices in the direction of the faces around the hole.

    Returns:
        ``(new_vertices, triangles)``: (0 or 1, 3) positions appended after ``vertices`` (the centroid,
        only for the fan fallback) and (t, 3) triangles indexing ``vertices`` plus the new ones.
    """
    reverse = loop[::-1]  # the cap runs against the faces' direction along the loop
    points = vertices[reverse]
    centroid = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - centroid)
    flat = (points - centroid) @ axes[:2].T
    if _signed_area_2d(flat) < 0:  # counter-clockwise in its plane, for ear clipping
        flat[:, 1] *= -1.0
    # ears are runs of consecutive corners, so the triangles follow `reverse` along the loop whatever
    # the projection's handedness
    tris = ear_clip(flat) if _is_simple(flat) else None
    if tris is not None:
        return np.zeros((0, 3)), reverse[tris]
    center = len(vertices)
    k = len(reverse)
    fan = np.column_stack([reverse, np.roll(reverse, -1), np.full(k, center)])
    return centroid[None, :], fan


def close_small_holes(
    vertices: np.ndarray, faces: np.ndarray, max_fraction: float, name: str, repairs: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """Cap every boundary loop that spans at most ``max_fraction`` of the bounding-box diagonal.

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) consistently wound, edge-manifold triangles.
        max_fraction: Largest loop bounding-box diagonal closed, relative to the mesh's.
        name: Name of the mesh for error messages.
        repairs: Receives a line describing what was closed.

    Returns:
        ``(vertices, faces)`` with the holes capped.

    Raises:
        InputError: If a hole is larger than the limit or the boundary is pinched (one line).
    """
    from warpfem.errors import InputError

    try:
        loops = boundary_loops(faces)
    except ValueError as exc:
        raise InputError(f"{name}: not closed and the hole cannot be closed: {exc}") from None
    if not loops:
        return vertices, faces
    diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    spans = [float(np.linalg.norm(np.ptp(vertices[loop], axis=0))) / diag for loop in loops]
    if max(spans) > max_fraction:
        raise InputError(
            f"{name}: open surface, it encloses no volume: {len(loops)} holes, the largest spans {max(spans):.3g} of"
            f" the bounding-box diagonal (holes up to {max_fraction:g} are closed automatically)"
        )
    new_vertices, new_faces = [vertices], [faces]
    count = len(vertices)
    for loop in loops:
        extra, tris = cap_loop(vertices, loop)
        new_faces.append(np.where(tris >= len(vertices), tris - len(vertices) + count, tris))
        new_vertices.append(extra)
        count += len(extra)
    repairs.append(
        f"closed {len(loops)} holes ({sum(len(loop) for loop in loops)} boundary edges, largest spanning"
        f" {max(spans):.3g} of the diagonal)"
    )
    return np.concatenate(new_vertices), np.concatenate(new_faces).astype(faces.dtype)


def shell_labels(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """Return the connected component (shell) of every face, components connected through vertices.

    Args:
        faces: (m, 3) vertex indices.
        vertex_count: Number of vertices.

    Returns:
        (m,) int64 labels 0..s-1.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(vertex_count, vertex_count))
    _, vertex_label = connected_components(graph, directed=False)
    _, labels = np.unique(vertex_label[faces[:, 0]], return_inverse=True)
    return labels.reshape(-1)


def _shell_volumes(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    per_face = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return np.bincount(labels, weights=per_face)


def select_shells(
    vertices: np.ndarray, faces: np.ndarray, shells: str | int, name: str, repairs: list[str]
) -> tuple[np.ndarray, bool]:
    """Orient every shell outward and keep the shells that ``shells`` asks for.

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) closed, consistently wound triangles.
        shells: ``"merge"`` (keep all as one body), ``"largest"`` (keep the largest by volume),
            ``"error"`` (reject several shells) or an int k (keep the k-th largest, 0-based; one body per
            shell is made by preparing each k).
        name: Name of the mesh for error messages.
        repairs: Receives lines describing flips and dropped shells.

    Returns:
        ``(faces, overlapping)``: the kept faces, each shell wound outward, and whether a kept shell lies
        inside or crosses another (the body is then the union, rebuilt as an outer surface).

    Raises:
        InputError: For a bad ``shells`` value, several shells with ``"error"``, an index out of range, or
            a shell enclosing zero volume.
    """
    from warpfem.errors import InputError

    if not (shells in ("merge", "largest", "error") or (isinstance(shells, int) and shells >= 0)):
        raise InputError(f"{name}: shells must be 'merge', 'largest', 'error' or a shell index >= 0, got {shells!r}")
    labels = shell_labels(faces, len(vertices))
    volumes = _shell_volumes(vertices, faces, labels)
    diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    flat = np.abs(volumes) <= 1e-12 * diag**3
    if np.all(flat):
        what = "encloses zero volume (flat surface)" if len(volumes) == 1 else "all its shells enclose zero volume"
        raise InputError(f"{name}: {what}: there is nothing to fill with tets")
    if np.any(flat):  # flaps and sheets (capped or two-sided) carry no volume: the body is the rest
        repairs.append(
            f"removed {int(flat.sum())} shells enclosing no volume (flaps or sheets, {int(flat[labels].sum())} faces)"
        )
        faces, labels = faces[~flat[labels]], np.cumsum(~flat)[labels[~flat[labels]]] - 1
        volumes = volumes[~flat]
    count = len(volumes)
    inward = volumes < 0
    if np.any(inward):
        faces = np.where(inward[labels][:, None], faces[:, ::-1], faces)
        repairs.append("flipped inward winding" if count == 1 else f"flipped {int(inward.sum())} inward shells")
    if count == 1:
        return faces, False
    order = np.argsort(-np.abs(volumes))
    if shells == "error":
        raise InputError(f"{name}: {count} separate shells (choose shells = merge, largest or an index)")
    if shells == "largest" or isinstance(shells, int):
        index = 0 if shells == "largest" else int(shells)
        if index >= count:
            raise InputError(f"{name}: shell index {index} out of range ({count} shells)")
        repairs.append(f"kept shell {index} of {count} (by volume)")
        return faces[labels == order[index]], False
    repairs.append(f"merged {count} shells into one body")
    return faces, _any_nested(vertices, faces, labels, count)


def _any_nested(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, count: int) -> bool:
    """Whether a vertex of some shell lies inside another shell (winding number >= 1/2).

    Only the shells whose bounding box holds the probe vertex can hold it: a pile of 44 parts is tested
    against its neighbours, not against every other part.
    """
    import igl

    corners = vertices[faces]  # (m, 3, 3)
    lower = np.full((count, 3), np.inf)
    upper = np.full((count, 3), -np.inf)
    np.minimum.at(lower, labels, corners.min(axis=1))
    np.maximum.at(upper, labels, corners.max(axis=1))
    for s in range(count):
        probe = vertices[faces[labels == s][0, 0]]
        around = np.all((lower <= probe) & (probe <= upper), axis=1)
        around[s] = False
        if not around.any():
            continue
        others = faces[around[labels]].astype(np.int64)
        if abs(float(igl.winding_number(vertices, others, probe[None, :])[0])) >= 0.5:
            return True
    return False


def _half_edge_pairs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-edges (corner 3f+k to corner 3f+k+1) and, for edges of exactly two faces, the pairs sharing one.

    Returns:
        ``(counts, first, second)``: faces per undirected edge of every half-edge (3m,), and the two
        half-edge indices of each edge shared by exactly two faces.
    """
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2).astype(np.int64)
    _, inverse, counts = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    two = counts[inverse[order]] == 2
    paired = order[two].reshape(-1, 2)  # sorted by edge: each edge of two faces gives consecutive entries
    return counts[inverse], paired[:, 0], paired[:, 1]


def split_non_manifold(vertices: np.ndarray, faces: np.ndarray, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Give each fan of faces around a vertex its own copy of it, so that no edge is non-manifold.

    Two faces around a vertex belong to one fan when they share an edge of that vertex that has exactly two
    faces. At the ends of an edge of three or more faces (a flap welded onto a surface, two bodies sharing
    an edge), and where a boundary pinches, each fan gets its own vertex: the pieces become separate sheets
    or shells, which hole closing and shell selection then handle.

    Args:
        vertices: (n, 3) positions.
        faces: (m, 3) vertex indices.
        repairs: Receives a line saying how many edges and vertices were split.

    Returns:
        ``(vertices, faces)``: the split vertices are repeated (same positions), one per fan.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    counts, first, second = _half_edge_pairs(faces)
    corner_vertex = faces.reshape(-1).astype(np.int64)
    # half-edge h runs from corner h to corner _next_corner(h); the corners of a shared edge's two
    # half-edges at the same vertex are joined
    same = corner_vertex[first] == corner_vertex[second]  # both run the same way round
    a = [first, _next_corner(first)]
    b = [np.where(same, second, _next_corner(second)), np.where(same, _next_corner(second), second)]
    # a closed surface pinched at a vertex (cow.obj) stays as it is: only vertices on an edge of one or
    # of more than two faces are split
    loose = np.zeros(len(vertices), dtype=bool)
    odd = np.flatnonzero(counts != 2)
    loose[corner_vertex[odd]] = loose[corner_vertex[_next_corner(odd)]] = True
    kept = np.flatnonzero(~loose[corner_vertex])
    kept = kept[np.argsort(corner_vertex[kept], kind="stable")]
    chain = corner_vertex[kept[1:]] == corner_vertex[kept[:-1]]
    a, b = np.concatenate([*a, kept[:-1][chain]]), np.concatenate([*b, kept[1:][chain]])
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(corner_vertex), len(corner_vertex)))
    fans, label = connected_components(graph, directed=False)
    if fans == len(np.unique(corner_vertex)):
        return vertices, faces
    source = np.zeros(fans, dtype=np.int64)
    source[label] = corner_vertex
    split = int(np.sum(np.bincount(source, minlength=len(vertices)) > 1))
    edges = _count_edges(faces, counts)
    repairs.append(f"split {edges} non-manifold edges and {split} vertices where separate sheets met")
    return vertices[source], label.reshape(-1, 3).astype(faces.dtype)


def _next_corner(h: np.ndarray) -> np.ndarray:
    """The corner after corner ``h`` (3f+k) in its face."""
    return h - h % 3 + (h % 3 + 1) % 3


def _count_edges(faces: np.ndarray, counts: np.ndarray) -> int:
    """Number of undirected edges of more than two faces."""
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    return len(np.unique(np.sort(directed[counts > 2], axis=1), axis=0))


def orient_consistently(faces: np.ndarray, name: str, repairs: list[str]) -> np.ndarray:
    """Turn the faces wound against their neighbours, so that every sheet is wound one way round.

    Faces sharing an edge of two faces are wound consistently when they run along it in opposite
    directions. Within each connected sheet the smaller set of faces is turned (a few flipped faces in
    a scan); which side is outward is decided later, per shell, by its signed volume.

    Args:
        faces: (m, 3) vertex indices, no edge shared by more than two faces.
        name: Name of the mesh for error messages.
        repairs: Receives a line saying how many faces were turned.

    Returns:
        (m, 3) faces, consistently wound.

    Raises:
        InputError: If a sheet cannot be wound consistently (it is one-sided, like a Moebius strip).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    from warpfem.errors import InputError

    _, first, second = _half_edge_pairs(faces)
    corner_vertex = faces.reshape(-1)
    same = corner_vertex[first] == corner_vertex[second]
    if not same.any():
        return faces
    f1, f2 = first // 3, second // 3
    # relation 2: turn exactly one of the two faces; 1: turn both or neither
    graph = coo_matrix((1 + same, (f1, f2)), shape=(len(faces), len(faces))).tocsr()
    graph = graph + graph.T
    _, component = connected_components(graph, directed=False)
    turn = np.zeros(len(faces), dtype=bool)
    for sheet in np.unique(component[f1[same]]):
        root = int(np.argmax(component == sheet))
        order, parent = breadth_first_order(graph, root, directed=False, return_predecessors=True)
        relation = np.asarray(graph[parent[order[1:]], order[1:]]).reshape(-1) == 2
        for node, link, up in zip(order[1:].tolist(), relation.tolist(), parent[order[1:]].tolist(), strict=True):
            turn[node] = turn[up] ^ link
        if np.count_nonzero(turn[order]) * 2 > len(order):
            turn[order] = ~turn[order]
    if np.any((turn[f1] != turn[f2]) != same):
        raise InputError(
            f"{name}: one-sided surface (like a Moebius strip): it has no inside, so it encloses no volume"
        )
    repairs.append(f"turned {int(turn.sum())} faces wound against their neighbours")
    return np.where(turn[:, None], faces[:, ::-1], faces)
