"""kdrt.Client's distance queries against a real kdrt-server: compute_closest_points against a
brute-force closest point in numpy, the KDRD records equal to the C++ client's (the kdrt CLI),
inside / outside on a closed box against its known geometry, the bunny's closedness against an
edge count in numpy, open meshes (NaN signed distance, occupancy refused), chunking past the
server's max_distance_points, and the input and server errors."""

import os
import struct

import numpy as np
import pytest

import kdrt
from conftest import Server

# The closed box [0, 1]^3 as 12 outward-facing triangles.
BOX_VERTICES = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                         [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float32)
BOX_TRIANGLES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                          [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]],
                         dtype=np.uint32)


def brute_force_closest(vertices, triangles, points):
    """The closest point of every triangle to every point (Ericson, "Real-Time Collision
    Detection" 5.1.5, vectorised in float64); returns (distance, triangle) of the nearest."""
    p = points.astype(np.float64)[:, None, :]
    a, b, c = (vertices[triangles[:, k]].astype(np.float64)[None, :, :] for k in range(3))
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda x, y: np.sum(x * y, axis=-1)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v_face, w_face = vb * denom, vc * denom
        q = a + ab * v_face[..., None] + ac * w_face[..., None]
        # Edge ab, ac, bc and the corners, in the order of the Voronoi tests.
        t_ab = d1 / (d1 - d3)
        q = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + ab * t_ab[..., None], q)
        t_ac = d2 / (d2 - d6)
        q = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + ac * t_ac[..., None], q)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        q = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None],
                     b + (c - b) * t_bc[..., None], q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, q)
    d = np.linalg.norm(p - q, axis=-1)
    return d.min(axis=1), d.argmin(axis=1), np.sort(d, axis=1)


def edge_counts(vertices, triangles):
    """(boundary, non-manifold, misoriented) edges, vertices matched by position, as
    proto/FORMATS.md defines a closed mesh."""
    _, ids = np.unique(vertices, axis=0, return_inverse=True)
    t = ids.reshape(-1)[triangles]
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    forward = directed[:, 0] < directed[:, 1]
    keys, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    forwards = np.bincount(inverse.reshape(-1), weights=forward, minlength=keys.shape[0])
    boundary = int(np.sum(counts == 1))
    nonmanifold = int(np.sum(counts > 2))
    misoriented = int(np.sum((counts == 2) & (forwards != 1)))
    return boundary, nonmanifold, misoriented


def read_off(path):
    with open(path) as f:
        words = [w for line in f for w in line.split("#")[0].split()]
    assert words[0] == "OFF"
    nv, nf = int(words[1]), int(words[2])
    v = np.array(words[4:4 + 3 * nv], dtype=np.float32).reshape(nv, 3)
    faces, i = [], 4 + 3 * nv
    for _ in range(nf):
        k = int(words[i])
        corners = [int(x) for x in words[i + 1:i + 1 + k]]
        faces += [[corners[0], corners[j], corners[j + 1]] for j in range(1, k - 1)]
        i += 1 + k
    return v, np.array(faces, dtype=np.uint32)


@pytest.fixture(scope="module")
def box(server):
    with kdrt.Client(server.url) as c:
        return c.upload(BOX_VERTICES, BOX_TRIANGLES)


def test_closest_points_equal_brute_force(client):
    rng = np.random.default_rng(5)
    centres = rng.uniform(0, 1, (60, 1, 3))
    vertices = (centres + rng.uniform(-0.15, 0.15, (60, 3, 3))).reshape(-1, 3).astype(np.float32)
    triangles = np.arange(180, dtype=np.uint32).reshape(60, 3)
    mesh = client.upload(vertices, triangles)
    points = rng.uniform(-0.3, 1.3, (20, 20, 3)).astype(np.float32)
    got = client.compute_closest_points(mesh, points)
    assert got["points"].shape == (20, 20, 3) and got["points"].dtype == np.float32
    assert got["distance"].shape == (20, 20) and got["distance"].dtype == np.float32
    assert got["primitive_ids"].dtype == np.uint32
    assert got["primitive_uvs"].shape == (20, 20, 2)
    assert got["features"].dtype == np.uint8 and got["features"].max() <= 6
    distance, prim, ordered = brute_force_closest(vertices, triangles, points.reshape(-1, 3))
    np.testing.assert_allclose(got["distance"].reshape(-1), distance, rtol=1e-5, atol=1e-6)
    clear = ordered[:, 1] - ordered[:, 0] > 1e-5  # the nearest triangle is unambiguous
    assert clear.sum() > 300
    np.testing.assert_array_equal(got["primitive_ids"].reshape(-1)[clear], prim[clear])
    # The point is the barycentric combination of its triangle's corners, at that distance.
    ids = got["primitive_ids"].reshape(-1)
    u, v = got["primitive_uvs"].reshape(-1, 2).T.astype(np.float64)
    corners = vertices[triangles[ids]].astype(np.float64)
    q = (1 - u - v)[:, None] * corners[:, 0] + u[:, None] * corners[:, 1] + v[:, None] * corners[:, 2]
    np.testing.assert_allclose(got["points"].reshape(-1, 3), q, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(points.reshape(-1, 3) - q, axis=1), distance,
                               atol=1e-5)
    np.testing.assert_array_equal(client.compute_distance(mesh, points), got["distance"])


def test_records_equal_the_cpp_clients(client, bunny, cli, server, tmp_path):
    rng = np.random.default_rng(9)
    lo, hi = bunny.bounds
    points = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (3000, 3)).astype(np.float32)
    path = tmp_path / "points.kdrp"
    path.write_bytes(struct.pack("<4sHHII", b"KDRP", 1, 0, len(points), 0) +
                     points.astype("<f4").tobytes())
    for signed in (False, True):
        out = tmp_path / f"answers-{signed}.kdrd"
        cli("--server", server.url, "distance", bunny.id, str(path), "-o", str(out),
            *(["--signed"] if signed else []))
        want = np.frombuffer(out.read_bytes(), dtype=kdrt._wire.DISTANCE_RECORD, offset=16)
        if signed:
            got = client.compute_signed_distance(bunny, points)
            side = want["side"]
            expected = np.where(side == 1, -want["distance"],
                                np.where(side == 0, want["distance"], np.nan))
            np.testing.assert_array_equal(got, expected.astype(np.float32))
        else:
            got = client.compute_closest_points(bunny, points)
            np.testing.assert_array_equal(got["distance"], want["distance"])
            np.testing.assert_array_equal(got["primitive_ids"], want["prim"])
            np.testing.assert_array_equal(got["primitive_uvs"][:, 0], want["u"])
            np.testing.assert_array_equal(got["primitive_uvs"][:, 1], want["v"])
            np.testing.assert_array_equal(got["points"], want["point"])
            np.testing.assert_array_equal(got["features"], want["feature"])


def test_bunny_closedness_is_the_edge_count(client, bunny, data_dir):
    vertices, triangles = read_off(os.path.join(data_dir, "bunny00.off"))
    boundary, nonmanifold, misoriented = edge_counts(vertices, triangles)
    surface = client.surface(bunny)
    if boundary == nonmanifold == misoriented == 0:
        assert surface == "closed"
    else:
        assert surface == (f"not closed: {boundary} boundary edges, {nonmanifold} non-manifold "
                           f"edges, {misoriented} misoriented edges")
    assert edge_counts(BOX_VERTICES, BOX_TRIANGLES) == (0, 0, 0)


def test_box_inside_and_outside(client, box):
    assert client.surface(box) == "closed"
    rng = np.random.default_rng(3)
    inside = rng.uniform(0.05, 0.95, (500, 3)).astype(np.float32)
    outside = rng.uniform(-1, 2, (2000, 3)).astype(np.float32)
    outside = outside[np.any((outside < -0.05) | (outside > 1.05), axis=1)]
    points = np.concatenate([inside, outside])
    occupancy = client.compute_occupancy(box, points)
    assert occupancy.dtype == np.float32
    np.testing.assert_array_equal(occupancy[:len(inside)], 1.0)
    np.testing.assert_array_equal(occupancy[len(inside):], 0.0)
    # The box's distance: to the nearest face inside, to the clamped point outside.
    p = points.astype(np.float64)
    depth = np.min(np.concatenate([p, 1 - p], axis=1), axis=1)
    gap = np.linalg.norm(p - np.clip(p, 0, 1), axis=1)
    truth = np.where(np.all((p > 0) & (p < 1), axis=1), -depth, gap)
    signed = client.compute_signed_distance(box, points)
    np.testing.assert_allclose(signed, truth, rtol=1e-5, atol=1e-6)
    assert (signed[:len(inside)] < 0).all() and (signed[len(inside):] > 0).all()
    # Leading dimensions are kept.
    assert client.compute_occupancy(box, points[:24].reshape(2, 3, 4, 3)).shape == (2, 3, 4)


def test_max_distance_leaves_far_points_without_an_answer(client, box):
    points = np.array([[0.5, 0.5, 1.1], [0.5, 0.5, 3.0], [0.5, 0.5, 0.5]], dtype=np.float32)
    got = client.compute_closest_points(box, points, max_distance=0.2)
    np.testing.assert_allclose(got["distance"][0], 0.1, rtol=1e-5)
    assert got["distance"][1] == np.inf and got["distance"][2] == np.inf
    assert got["primitive_ids"][1] == kdrt.NO_HIT
    assert np.isnan(got["points"][1]).all()
    assert kdrt.FEATURES[got["features"][1]] == "none"
    signed = client.compute_signed_distance(box, points, max_distance=0.2)
    assert signed[0] > 0 and np.isnan(signed[1]) and np.isnan(signed[2])


def test_open_mesh_has_no_sign_and_no_occupancy(client):
    quad = client.upload(BOX_VERTICES[:4], BOX_TRIANGLES[:2])
    assert client.surface(quad) == ("not closed: 4 boundary edges, 0 non-manifold edges, "
                                    "0 misoriented edges")
    points = np.array([[0.5, 0.5, 1.0], [0.5, 0.5, -1.0]], dtype=np.float32)
    assert np.isnan(client.compute_signed_distance(quad, points)).all()
    np.testing.assert_allclose(client.compute_distance(quad, points), [1.0, 1.0])
    with pytest.raises(kdrt.Error) as err:
        client.compute_occupancy(quad, points)
    assert err.value.kind == "input"
    assert err.value.title == "mesh not closed"
    assert "4 boundary edges" in err.value.detail


def test_points_in_chunks_past_the_servers_limit(data_dir):
    # The server takes 250 points a request; the client's chunks (65536, then 100) are larger
    # or smaller: the answers are the same.
    server = Server("--max-distance-points", "250")
    try:
        with kdrt.Client(server.url) as big, kdrt.Client(server.url, chunk_rays=100) as small:
            mesh = big.upload(BOX_VERTICES, BOX_TRIANGLES)
            points = np.random.default_rng(1).uniform(-0.5, 1.5, (1000, 3)).astype(np.float32)
            a = big.compute_closest_points(mesh, points)
            b = small.compute_closest_points(mesh, points)
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])
            np.testing.assert_array_equal(big.compute_signed_distance(mesh, points),
                                          small.compute_signed_distance(mesh, points))
    finally:
        server.stop()


def test_errors_name_what_is_wrong(client, box):
    points = np.zeros((10, 3), dtype=np.float32)
    points[7, 1] = np.nan
    with pytest.raises(kdrt.Error) as err:
        client.compute_distance(box, points)
    assert err.value.kind == "input" and err.value.code == "non_finite_point"
    assert "point 7: field y is NaN" in err.value.detail
    points[7, 1] = 0
    points[2, 2] = -np.inf
    with pytest.raises(kdrt.Error) as err:
        client.compute_distance(box, points)
    assert "point 2: field z is -inf" in err.value.detail
    with pytest.raises(kdrt.Error) as err:
        client.compute_distance(box, np.zeros((4, 2)))
    assert err.value.kind == "input" and "shape (..., 3)" in err.value.detail
    with pytest.raises(kdrt.Error) as err:
        client.compute_distance("a" * 64, np.zeros((4, 3)))
    assert err.value.status == 404
    with pytest.raises(kdrt.Error) as err:
        client.compute_distance(box, np.zeros((4, 3)), max_distance=-1)
    assert err.value.status == 400 and "max_distance" in err.value.detail
