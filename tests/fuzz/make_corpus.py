#!/usr/bin/env python3
"""Writes the seed corpora in tests/fuzz/corpus/<target>/: a few valid and invalid inputs per
decoder/parser, including hostile headers (huge counts, wrong sizes). Deterministic; rerun after
changing it. Inputs found by a real fuzzer are added by hand as corpus/<target>/crash-*."""

import math
import os
import struct

HERE = os.path.dirname(os.path.abspath(__file__))


def write(target, name, data):
    directory = os.path.join(HERE, "corpus", target)
    os.makedirs(directory, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(directory, name), "wb") as f:
        f.write(data)


def header(magic, count, version=1, flags=0, reserved=0):
    return magic + struct.pack("<HHII", version, flags, count, reserved)


INF = math.inf
NAN = math.nan

# ---- KDRR ----
RAYS = [(0, 0, -5, 0, 0, 0, 1, 100), (1, 2, 3, 0.5, -1, 0, 0, INF)]
ray_body = b"".join(struct.pack("<8f", *r) for r in RAYS)
write("rays", "valid_two_rays", header(b"KDRR", 2) + ray_body)
write("rays", "valid_occlusion", header(b"KDRR", 2, flags=1) + ray_body)
write("rays", "valid_empty", header(b"KDRR", 0))
write("rays", "nan_ray", header(b"KDRR", 1) + struct.pack("<8f", NAN, 0, 0, 0, 1, 0, 0, INF))
write("rays", "bad_magic", header(b"KDRH", 2) + ray_body)
write("rays", "bad_version", header(b"KDRR", 2, version=2) + ray_body)
write("rays", "bad_flags", header(b"KDRR", 2, flags=6) + ray_body)
write("rays", "bad_reserved", header(b"KDRR", 2, reserved=1) + ray_body)
write("rays", "short_body", header(b"KDRR", 3) + ray_body)
write("rays", "long_body", header(b"KDRR", 1) + ray_body)
write("rays", "huge_count", header(b"KDRR", 0xFFFFFFFF))
write("rays", "truncated_header", b"KDRR\x01\x00")

# ---- KDRP / KDRD (distance queries) ----
points = struct.pack("<3f", 0.25, 0.25, 2) + struct.pack("<3f", 5, 0, 0)
write("distances", "valid_points", header(b"KDRP", 2) + points)
write("distances", "nan_point", header(b"KDRP", 1) + struct.pack("<3f", 1, NAN, 3))
write("distances", "short_points", header(b"KDRP", 3) + points)
write("distances", "huge_points", header(b"KDRP", 0xFFFFFFFF))
found = struct.pack("<fIff3fBBH", 2, 4, 0.25, 0.25, 0.25, 0.25, 0, 0, 0, 0)
missing = struct.pack("<fIff3fBBH", INF, 0xFFFFFFFF, 0, 0, NAN, NAN, NAN, 7, 2, 0)
write("distances", "valid_distances", header(b"KDRD", 2, flags=1) + found + missing)
write("distances", "bad_feature", header(b"KDRD", 1) + struct.pack("<fIff3fBBH", 1, 0, 0, 0, 0, 0, 0, 9, 0, 0))
write("distances", "bad_flags", header(b"KDRD", 1, flags=2) + found)
write("distances", "points_text", "x,y,z\n1,2,3\n# c\n4 5 6 0 0 1\n")
write("distances", "points_text_bad", "1 2 3\n4 nan 6\n")

# ---- KDRI (raw render answers, raw_image target) ----
def kdri(channels, width, height, x, y, frame_width, frame_height, pixels, version=1, magic=b"KDRI"):
    return (magic + struct.pack("<HHIIIIII", version, channels, width, height, x, y, frame_width,
                                frame_height) + struct.pack("<%df" % len(pixels), *pixels))


write("raw_image", "valid_rgb", kdri(3, 2, 1, 1, 1, 4, 2, [0.5, 0.25, 1, 0, 0, 0]))
write("raw_image", "valid_rgba", kdri(4, 1, 1, 0, 0, 1, 1, [NAN, INF, -0.0, 1]))
write("raw_image", "valid_frame", kdri(3, 3, 2, 0, 0, 3, 2, [k / 18 for k in range(18)]))
write("raw_image", "bad_magic", kdri(3, 1, 1, 0, 0, 1, 1, [0, 0, 0], magic=b"KDRH"))
write("raw_image", "bad_version", kdri(3, 1, 1, 0, 0, 1, 1, [0, 0, 0], version=2))
write("raw_image", "bad_channels", kdri(2, 1, 1, 0, 0, 1, 1, [0, 0]))
write("raw_image", "empty_region", kdri(3, 0, 1, 0, 0, 1, 1, []))
write("raw_image", "outside_frame", kdri(3, 2, 1, 1, 0, 2, 1, [0] * 6))
write("raw_image", "wrapping_region", kdri(3, 2, 1, 0xFFFFFFFF, 0, 1, 1, [0] * 6))
write("raw_image", "huge_region", kdri(4, 0xFFFFFFFF, 0xFFFFFFFF, 0, 0, 0xFFFFFFFF, 0xFFFFFFFF, []))
write("raw_image", "short_body", kdri(3, 2, 1, 0, 0, 2, 1, [0] * 5))
write("raw_image", "long_body", kdri(3, 1, 1, 0, 0, 1, 1, [0] * 4))
write("raw_image", "truncated_header", b"KDRI\x01\x00\x03\x00")

# ---- KDRZ / KDRL / KDRB (sensor scans) ----
def kdrz(flags, width, height, planes, version=1):
    return b"KDRZ" + struct.pack("<HHII", version, flags, width, height) + planes


def kdrl(points, channels=2, steps=4, returns=2, count=None, flags=0, reserved=0):
    n = len(points) if count is None else count
    return (b"KDRL" + struct.pack("<HHIIIIQ", 1, flags, n, channels, steps, returns, reserved) +
            b"".join(struct.pack("<4f4I", *p) for p in points))


depth_planes = struct.pack("<2f", 2, INF) + struct.pack("<2I", 4, 0xFFFFFFFF)
normal_plane = struct.pack("<6f", 0, 0, -1, 0, 0, 0)
write("scans", "valid_depth", kdrz(0, 2, 1, depth_planes))
write("scans", "valid_depth_normals", kdrz(3, 2, 1, depth_planes + normal_plane))
write("scans", "depth_miss_with_depth", kdrz(0, 2, 1, struct.pack("<2f", 2, 3) + struct.pack("<2I", 4, 0xFFFFFFFF)))
write("scans", "depth_bad_flags", kdrz(4, 2, 1, depth_planes))
write("scans", "depth_short", kdrz(2, 2, 1, depth_planes))
write("scans", "depth_huge", kdrz(0, 0xFFFFFFFF, 0xFFFFFFFF, b""))
write("scans", "depth_zero_width", kdrz(0, 0, 1, b""))
cloud = [(2, 0, 0, 2, 1, 0, 0, 7), (0, 3, 0, 3, 1, 1, 0, 2), (0, 4, 0, 4, 1, 1, 1, 3)]
write("scans", "valid_cloud", kdrl(cloud))
write("scans", "valid_empty_cloud", kdrl([]))
write("scans", "cloud_out_of_order", kdrl(cloud[::-1]))
write("scans", "cloud_bad_channel", kdrl([(2, 0, 0, 2, 5, 0, 0, 7)]))
write("scans", "cloud_nan", kdrl([(NAN, 0, 0, 2, 1, 0, 0, 7)]))
write("scans", "cloud_miss", kdrl([(2, 0, 0, 2, 1, 0, 0, 0xFFFFFFFF)]))
write("scans", "cloud_huge", kdrl([], count=0xFFFFFFFF))
write("scans", "cloud_reserved", kdrl(cloud, reserved=1))
write("scans", "cloud_zero_returns", kdrl(cloud, returns=0))


def kdrb(records, channels=2, steps=4, returns=2, count=None, flags=0, reserved=0):
    n = len(records) if count is None else count
    return (b"KDRB" + struct.pack("<HHIIIIQ", 1, flags, n, channels, steps, returns, reserved) +
            b"".join(struct.pack("<f2I", *r) for r in records))


ranges = [(2, 1, 7), (3, 3, 2), (4, 3, 3)]
write("scans", "valid_ranges", kdrb(ranges))
write("scans", "valid_empty_ranges", kdrb([]))
write("scans", "ranges_out_of_order", kdrb(ranges[::-1]))
write("scans", "ranges_too_many_returns", kdrb(ranges, returns=1))
write("scans", "ranges_bad_beam", kdrb([(2, 8, 7)]))
write("scans", "ranges_nan", kdrb([(NAN, 1, 7)]))
write("scans", "ranges_miss", kdrb([(2, 1, 0xFFFFFFFF)]))
write("scans", "ranges_huge", kdrb([], count=0xFFFFFFFF))
write("scans", "ranges_beams_over_u32", kdrb([], channels=0x10001, steps=0x10000))
write("scans", "ranges_scene_flag", kdrb(ranges, flags=0x100))

# ---- KDRM / KDRC ----
def kdrm(flags, record, rays, offsets, counts, records, max_hits=2, reserved=0):
    return (struct.pack("<4sHHIIQII", b"KDRM", 1, flags, rays, record, offsets[-1], max_hits,
                        reserved) + struct.pack(f"<{len(offsets)}Q", *offsets) +
            struct.pack(f"<{len(counts)}I", *counts) + records)


full = struct.pack("<fIff", 1, 3, 0.25, 0.5) + struct.pack("<fIff", 2, 0, 0, 0.5)
write("multi_hits", "valid_full", kdrm(0, 16, 2, [0, 2, 2], [3, 0], full))
write("multi_hits", "valid_t_prim_normal_point",
      kdrm(0x1E, 32, 1, [0, 1], [1], struct.pack("<fI6f", 1, 3, 0, 0, 1, 0.5, 0.5, 0)))
write("multi_hits", "valid_empty", kdrm(0, 16, 0, [0], [], b""))
write("multi_hits", "bad_offsets", kdrm(0, 16, 2, [0, 3, 2], [3, 0], full))
write("multi_hits", "count_below_kept", kdrm(0, 16, 2, [0, 2, 2], [1, 0], full))
write("multi_hits", "record_mismatch", kdrm(1, 16, 2, [0, 2, 2], [3, 0], full))
write("multi_hits", "huge_hits", struct.pack("<4sHHIIQII", b"KDRM", 1, 0, 1, 16, 1 << 62, 2, 0))
write("multi_hits", "valid_counts", header(b"KDRC", 2) + struct.pack("<II", 3, 0))
write("multi_hits", "short_counts", header(b"KDRC", 2) + struct.pack("<I", 3))

# ---- KDRR, incremental (ray_stream): mode byte (1 declared size, 2 refuse non-finite, 4 windows),
# piece-size seed, body ----
for name, body in [("valid_two_rays", header(b"KDRR", 2) + ray_body),
                   ("valid_occlusion", header(b"KDRR", 2, flags=1) + ray_body),
                   ("nan_ray", header(b"KDRR", 2) + ray_body[:32] + struct.pack("<8f", NAN, 0, 0, 0, 1, 0, 0, INF)),
                   ("short_body", header(b"KDRR", 3) + ray_body),
                   ("long_body", header(b"KDRR", 1) + ray_body),
                   ("huge_count", header(b"KDRR", 0xFFFFFFFF) + ray_body)]:
    for mode in (0, 3, 7):
        write("ray_stream", "%s_mode%d" % (name, mode), bytes([mode, 17 * mode + 1]) + body)

# ---- scan requests (json target, first byte 4: job status and scan request decoders) ----
write("json", "scan_lidar", '4{"lidar": {"vertical_fov": [-10, 10], "channels": 4, "azimuth_steps": 8, '
      '"returns": 2, "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,1],[0,0,0,1]]}, "format": "ply"}')
write("json", "scan_pinhole", '4{"pinhole": {"intrinsics": {"fx": 10, "fy": 10, "cx": 2, "cy": 2, '
      '"width": 4, "height": 4}, "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,-2],[0,0,0,1]], '
      '"output": "range", "normals": true, "max_range": 9}, "format": "exr"}')
write("json", "scan_look_at", '4{"pinhole": {"camera": {"eye": [0,0,1], "look_at": [0,0,0], "fov": 30}, '
      '"width": 8, "height": 6}}')
write("json", "scan_bad", '4{"pinhole": {"camera": {"eye": [0,0,1]}, "width": 2}}')

# ---- scenes (scene target; first byte: 0 create, 1 stored, 2 poses, 3 edit, 4 KDRX, 5 plane) ----
MESH_A = "a" * 64
write("scene", "create", '\x00{"instances": [{"mesh": "%s", "transform": [1,0,0,0, 0,1,0,0, 0,0,1,2], '
      '"name": "shelf-1"}, {"mesh": "%s", "transform": [[0,-1,0,4],[1,0,0,0],[0,0,1,0],[0,0,0,1]]}]}'
      % (MESH_A, MESH_A))
write("scene", "create_bad_transform", '\x00{"instances": [{"mesh": "%s", "transform": [1,0,0]}]}' % MESH_A)
write("scene", "stored", '\x01{"format":"kdrt-scene","id":"%s","revision":3,"instances":[{"geometry_id":0,'
      '"mesh":"%s","transform":[1,0,0,0,0,1,0,0,0,0,1,2],"name":"a"}]}' % ("0" * 32, MESH_A))


def kdrs_checksum(data):
    """The KDRS (and tree blob) checksum, proto/FORMATS.md "Tree blob"."""
    mask = (1 << 64) - 1
    h = 0x9E3779B97F4A7C15 ^ len(data)
    padded = data + b"\0" * (8 - len(data) % 8)  # the zero-padded tail, even when empty
    for (w,) in struct.iter_unpack("<Q", padded):
        h ^= (w * 0xC2B2AE3D27D4EB4F) & mask
        h = (((h << 31) | (h >> 33)) & mask) * 0x9E3779B97F4A7C15 & mask
    h ^= h >> 33
    h = h * 0xFF51AFD7ED558CCD & mask
    return h ^ (h >> 33)


def kdrs(scene_id, revision, instances):
    """A KDRS revision file of (mesh id, 12 floats, name) instances."""
    meshes = list(dict.fromkeys(m for m, _, _ in instances))
    names = b"".join(n.encode() for _, _, n in instances)
    body = (b"KDRS" + struct.pack("<HHQ", 1, 0, revision) + scene_id.encode() +
            struct.pack("<IIII", len(instances), len(meshes), len(names), 0) +
            b"".join(m.encode() for m in meshes) +
            b"".join(struct.pack("<I", meshes.index(m)) for m, _, _ in instances) +
            b"".join(struct.pack("<12f", *t) for _, t, _ in instances) +
            bytes(len(n) for _, _, n in instances) + names)
    return body + struct.pack("<Q", kdrs_checksum(body))


write("scene", "stored_kdrs", b"\x01" + kdrs("0" * 32, 3, [(MESH_A, [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 2], "a"),
                                                           ("b" * 64, [0, -1, 0, 4, 1, 0, 0, 0, 0, 0, 1, 0], "")]))
write("scene", "poses", '\x02{"poses": [{"geometry_id": 3, "transform": [1,0,0,0.5,0,1,0,0,0,0,1,0]}, '
      '{"name": "car", "transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}')
write("scene", "edit", '\x03{"remove": [0, "a"], "add": [{"mesh": "%s", "name": "bus"}]}' % MESH_A)
POSE = struct.pack("<I12f", 2, 0, -1, 0, 1, 1, 0, 0, 2, 0, 0, 1, 3)
write("scene", "kdrx", b"\x04" + header(b"KDRX", 1) + POSE)
write("scene", "kdrx_nan", b"\x04" + header(b"KDRX", 1) + POSE[:8] + struct.pack("<f", NAN) + POSE[12:])
write("scene", "kdrx_huge", b"\x04" + header(b"KDRX", 0xFFFFFFFF) + POSE)
HITS = struct.pack("<fIff", 5, 7, 0.25, 0.5) + struct.pack("<fIff", INF, 0xFFFFFFFF, 0, 0)
write("scene", "kdrh_plane", b"\x05" + header(b"KDRH", 2, flags=0x100) + HITS + struct.pack("<II", 3, 0xFFFFFFFF))
write("scene", "kdrz_plane_short", b"\x05" + b"KDRZ" + struct.pack("<HHII", 1, 0x100, 1000, 1000) + b"\x00" * 8)

# ---- scene and pose text files (scene_text target; first byte: even the scene text, odd the pose
# text) ----
MESH_B = "0123456789abcdef" * 4
write("scene_text", "scene", '\x00# geometry ids 0, 1, 2\n%s\n%s 0.5 0 0 1.2  0 0.5 0 0.1  0 0 0.5 0  crate\n'
      '%s, -1, 0.5, 0, far\r\n\n  # indented comment\n%s\t1e-3\t-2.5E+2\t0x1p3\n' % (MESH_A, MESH_B, MESH_A, MESH_B))
write("scene_text", "scene_bad_mesh", '\x00%s\nABC 1 2 3\n' % MESH_A)
write("scene_text", "scene_bad_count", '\x00%s 1 2\n' % MESH_A)
write("scene_text", "scene_bad_number", '\x00%s 1e40 0 0\n%s nan 0 0 n\n%s inf 1 2\n' % (MESH_A, MESH_A, MESH_A))
write("scene_text", "scene_twice_named", '\x00%s a\n%s a\n' % (MESH_A, MESH_B))
write("scene_text", "scene_too_many", '\x00' + ('%s\n' % MESH_A) * 17)
write("scene_text", "poses", '\x01# poses\n0 1 0 0 0.5  0 1 0 0  0 0 1 0\ncrate -1 0.5 0\n4294967295, 0, 0, -0\n')
write("scene_text", "poses_bad", '\x01crate\n')
write("scene_text", "poses_big_id", '\x014294967296 0 0 0\n1.5 0 0 0\n-3 1 1 1\n')
write("scene_text", "poses_empty", '\x01\n# nothing\n\r\n')

# ---- problem+json (json target, first byte 3: mesh list and problem decoders) ----
write("json", "problem", '3{"type":"urn:kdrt:problem:forbidden","title":"Forbidden","status":403,'
      '"detail":"DELETE /v1/meshes/{id} needs a token with the role write","code":"write",'
      '"instance":"/v1/meshes/ab","request_id":"0000000000000007","retry_after":1,"limit":5,"line":2}')

# ---- the client's HTTP answer reader (http_answer): the server's whole answer ----
write("http_answer", "content_length", "HTTP/1.1 200 OK\r\nContent-Type: application/x-kdrt-hits\r\n"
      "Content-Length: 5\r\nX-Request-Id: 0000000000000001\r\n\r\nhello")
write("http_answer", "chunked", "HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n"
      "3;ext=1\r\nabc\r\n0\r\nTrailer: x\r\n\r\n")
write("http_answer", "close_framing", "HTTP/1.0 200 OK\r\nContent-Type: image/png\r\n\r\nbody to the end")
write("http_answer", "continue_then_503", "HTTP/1.1 100 Continue\r\n\r\nHTTP/1.1 503 Over capacity\r\n"
      "Retry-After: 1\r\nContent-Type: application/problem+json\r\nContent-Length: 2\r\n"
      "Connection: close\r\n\r\n{}")
write("http_answer", "too_large", "HTTP/1.1 200 OK\r\nContent-Length: 999999\r\n\r\nabc")
write("http_answer", "two_lengths", "HTTP/1.1 200 OK\r\nContent-Length: 1\r\ncontent-length: 2\r\n\r\nab")
write("http_answer", "bad_status", "HTTP/1.1 2x0 OK\r\n\r\n")
write("http_answer", "not_http", "SSH-2.0-OpenSSH_9.2\r\n\r\n")
write("http_answer", "truncated_chunk", "HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nff\r\nshort")
write("http_answer", "bad_chunk_size", "HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n")
# (crash-empty-body-*: found by http_answer_fuzz, an empty body memcpy'd from a null buffer.)
write("http_answer", "gzip_encoding", "HTTP/1.1 200 OK\r\nTransfer-Encoding: gzip\r\n\r\n")

# ---- KDRH ----
hit_body = struct.pack("<fIff", 5, 7, 0.25, 0.5) + struct.pack("<fIff", INF, 0xFFFFFFFF, 0, 0)
write("hits", "valid_two_hits", header(b"KDRH", 2) + hit_body)
write("hits", "valid_empty", header(b"KDRH", 0))
write("hits", "bad_flags", header(b"KDRH", 2, flags=1) + hit_body)
write("hits", "short_body", header(b"KDRH", 2) + hit_body[:-1])
write("hits", "huge_count", header(b"KDRH", 0x80000000) + hit_body)
write("hits", "rays_magic", header(b"KDRR", 1) + hit_body)

# ---- KDRO ----
write("occlusion", "valid_two", header(b"KDRO", 2) + b"\x01\x00")
write("occlusion", "valid_empty", header(b"KDRO", 0))
write("occlusion", "bad_value", header(b"KDRO", 3) + b"\x01\x00\x02")
write("occlusion", "long_body", header(b"KDRO", 1) + b"\x01\x00")
write("occlusion", "huge_count", header(b"KDRO", 0xFFFFFFFF) + b"\x01")
write("occlusion", "bad_reserved", header(b"KDRO", 1, reserved=0xFFFFFFFF) + b"\x01")

# ---- OBJ ----
SQUARE = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
write("obj", "valid_square", SQUARE + "f 1 2 3 4\n")
write("obj", "valid_forms", SQUARE + "vt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1\nf 1//1 3//1 4//1\nf -4/1 -2/1 -1/1\n")
write("obj", "valid_misc", "# c\r\nmtllib a.mtl\r\no x\r\ng y\r\ns 1\r\nusemtl m\r\nv 0 0 0 1\r\n"
      "v 1 0 0 1 0.5 0.5 0.5\r\nv 0 \\\r\n1 0\r\nf 1 2 \\\n3\r\nl 1 2\r\n")
write("obj", "face_before_vertex", "f 1 2 3\n" + SQUARE)
write("obj", "nan_vertex", "v nan 0 0\n")
write("obj", "huge_index", SQUARE + "f 1 2 4294967297\n")
write("obj", "index_zero", SQUARE + "f 0 1 2\n")
write("obj", "two_corners", SQUARE + "f 1 2\n")
write("obj", "bad_corner", SQUARE + "f 1/ 2// 3/x/4\n")
write("obj", "binary_garbage", bytes(range(256)))
write("obj", "long_polygon", SQUARE + "f " + " ".join(str(1 + i % 4) for i in range(2000)) + "\n")

# ---- OFF ----
write("off", "valid_tetra", "OFF\n4 4 6\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
write("off", "valid_comments_quads", "# hi\nOFF 4 1 0 # counts here\n\n0 0 0\n1 0 0\n# x\n1 1 0\n0 1 0\n4 0 1 2 3 1 0 0\n")
write("off", "valid_coff", "COFF\n3 1 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n3 0 1 2\n")
write("off", "huge_counts", "OFF\n4294967295 4294967295 0\n0 0 0\n")
write("off", "big_counts_little_data", "OFF\n200000000 900000000 0\n0 0 0\n")
write("off", "truncated", "OFF\n3 1 0\n0 0 0\n1 0")
write("off", "index_out_of_range", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n")
write("off", "huge_polygon", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n4294967295 0 1 2\n")
write("off", "inf_vertex", "OFF\n3 1 0\n0 0 0\n1 inf 0\n0 1 0\n3 0 1 2\n")
write("off", "bad_header", "4OFF\n1 0 0\n0 0 0 0\n")

# ---- PLY ----
PLY_HEAD = ("ply\nformat {fmt} 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
TRI = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]


def ply_binary(order):
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    body = b"".join(struct.pack(order + "3f", *v) for v in TRI) + struct.pack(order + "B3i", 3, 0, 1, 2)
    return PLY_HEAD.format(fmt=fmt).encode() + body


write("ply", "valid_ascii", PLY_HEAD.format(fmt="ascii") + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
write("ply", "valid_le", ply_binary("<"))
write("ply", "valid_be", ply_binary(">"))
write("ply", "valid_extras",
      "ply\nformat ascii 1.0\ncomment c\nelement vertex 4\nproperty double x\nproperty list uchar float w\n"
      "property int y\nproperty uchar z\nelement edge 1\nproperty list int int e\nelement face 1\n"
      "property list ushort uint vertex_index\nproperty float q\nend_header\n"
      "0 0 0 0\n1 1 5 0 0\n1 0 1 0\n0 2 1 2 1 3\n2 0 1\n4 0 1 2 3 0.5\n")
write("ply", "huge_vertex_count", PLY_HEAD.format(fmt="binary_little_endian").replace("vertex 3", "vertex 4000000000"))
write("ply", "big_vertex_count_little_data",
      PLY_HEAD.format(fmt="binary_little_endian").replace("vertex 3", "vertex 200000000").encode() + b"\0" * 40)
write("ply", "huge_list_count", PLY_HEAD.format(fmt="binary_little_endian").replace("uchar int", "uint int").encode()
      + b"".join(struct.pack("<3f", *v) for v in TRI) + struct.pack("<I", 0xFFFFFFFF) + b"\0" * 12)
write("ply", "zero_property_element_huge_count",
      "ply\nformat binary_little_endian 1.0\nelement nothing 18446744073709551615\nend_header\n")
write("ply", "missing_end_header", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n")
write("ply", "unknown_format", "ply\nformat binary_middle_endian 1.0\nend_header\n")
write("ply", "nan_binary", PLY_HEAD.format(fmt="binary_little_endian").encode()
      + struct.pack("<9f", 0, 0, 0, NAN, 0, 0, 0, 1, 0) + struct.pack("<B3i", 3, 0, 1, 2))
write("ply", "truncated_binary", ply_binary("<")[:-5])

# ---- STL ----
FACET = "facet normal 0 0 1\n outer loop\n  vertex 0 0 0\n  vertex 1 0 0\n  vertex 0 1 0\n endloop\nendfacet\n"


def stl_binary(count, triangles, head=b"kdrt corpus"):
    out = head.ljust(80, b"\0") + struct.pack("<I", count)
    for t in triangles:
        out += struct.pack("<12fH", 0, 0, 1, *t, 0)
    return out


TRIS = [(0, 0, 0, 1, 0, 0, 0, 1, 0), (1, 1, 1, 2, 1, 1, 1, 2, 1)]
write("stl", "valid_ascii", "solid s\n" + FACET + FACET + "endsolid s\n")
write("stl", "valid_binary", stl_binary(2, TRIS))
write("stl", "valid_binary_solid_header", stl_binary(2, TRIS, b"solid looks like ascii"))
write("stl", "valid_multi_solid", "solid a\n" + FACET + "endsolid a\nsolid b\n" + FACET + "endsolid b\n")
write("stl", "huge_count", stl_binary(0xFFFFFFFF, []))
write("stl", "truncated_binary", stl_binary(3, TRIS))
write("stl", "missing_endsolid", "solid s\n" + FACET)
write("stl", "nan_binary", stl_binary(1, [(0, 0, 0, NAN, 0, 0, 0, 1, 0)]))
write("stl", "four_vertices", "solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n"
      "vertex 0 1 0\nvertex 1 1 0\nendloop\nendfacet\nendsolid\n")
write("stl", "tiny", "sol")

# ---- raw ----
def raw(vertex_count, triangle_count, positions, indices):
    return (struct.pack("<II", vertex_count, triangle_count) + struct.pack("<%df" % len(positions), *positions)
            + struct.pack("<%dI" % len(indices), *indices))


QUAD = [0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0]
write("raw", "valid_quad", raw(4, 2, QUAD, [0, 1, 2, 0, 2, 3]))
write("raw", "valid_empty", raw(0, 0, [], []))
write("raw", "huge_counts", raw(0xFFFFFFFF, 0xFFFFFFFF, [], []))
write("raw", "big_counts_little_data", raw(200000000, 0, QUAD, []))
write("raw", "truncated", raw(4, 2, QUAD, [0, 1, 2, 0, 2, 3])[:-3])
write("raw", "index_out_of_range", raw(4, 1, QUAD, [0, 1, 4]))
write("raw", "nan_vertex", raw(4, 0, QUAD[:5] + [NAN] + QUAD[6:], []))
write("raw", "short_header", b"\x04\x00\x00")
