"""Headless preview rendering: smooth vertex normals and a ray-casting kernel over one ``wp.Mesh``.

One primary ray per pixel against the mesh BVH and the ground plane; a shadow ray toward the key light
from every hit; on the ground a second ray along the up axis darkens the ground under a body (a soft
contact shadow). Shading: hemispheric ambient plus a Lambert/Blinn key light, an anti-aliased grid on the
ground, fog toward the horizon, sRGB-like gamma, 8-bit RGB out.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.kernel
def zero_normals(normals_out: wp.array(dtype=wp.vec3)):
    """Set every vertex normal to zero before accumulation."""
    normals_out[wp.tid()] = wp.vec3(0.0)


@wp.kernel
def accumulate_normals(
    points: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    normals_out: wp.array(dtype=wp.vec3),
):
    """Add each face's area-weighted normal to its three vertices (normalised where used)."""
    f = faces[wp.tid()]
    a = points[f[0]]
    n = wp.cross(points[f[1]] - a, points[f[2]] - a)
    wp.atomic_add(normals_out, f[0], n)
    wp.atomic_add(normals_out, f[1], n)
    wp.atomic_add(normals_out, f[2], n)


@wp.func
def grid_line(coord: float, spacing: float, half_width: float, footprint: float) -> float:
    """Coverage in [0, 1] of a pixel of world width ``footprint`` by grid lines every ``spacing``."""
    u = coord / spacing
    d = wp.abs(u - wp.round(u)) * spacing
    cover = wp.clamp((half_width + 0.5 * footprint - d) / footprint, 0.0, 1.0)
    return cover * wp.clamp(1.0 - footprint / (0.5 * spacing), 0.0, 1.0)


@wp.func
def to_byte(c: float) -> wp.uint8:
    """Linear intensity to an 8-bit value with gamma 2.2."""
    return wp.uint8(int(wp.pow(wp.clamp(c, 0.0, 1.0), 1.0 / 2.2) * 255.0 + 0.5))


@wp.kernel
def render(
    mesh: wp.uint64,
    normals: wp.array(dtype=wp.vec3),
    face_body: wp.array(dtype=wp.int32),
    body_colors: wp.array(dtype=wp.vec3),
    eye: wp.vec3,
    forward: wp.vec3,
    right: wp.vec3,
    up_screen: wp.vec3,
    light: wp.vec3,
    up: wp.vec3,
    ground_on: int,
    ground_height: float,
    ground_u: wp.vec3,
    ground_v: wp.vec3,
    grid_spacing: float,
    pixel_angle: float,
    scene_size: float,
    fog_distance: float,
    image_out: wp.array3d(dtype=wp.uint8),
):
    """Shade pixel (row i, column j) of ``image_out`` (height, width, 3).

    ``right`` and ``up_screen`` are the camera axes scaled by the half-extent of the image plane at
    distance 1 (tan of the half field of view), so that pixel (i, j) looks along
    ``forward + x right + y up_screen`` with x, y in [-1, 1]. ``light`` points toward the key light.
    """
    i, j = wp.tid()
    height = image_out.shape[0]
    width = image_out.shape[1]
    x = (float(j) + 0.5) / float(width) * 2.0 - 1.0
    y = 1.0 - (float(i) + 0.5) / float(height) * 2.0
    d = wp.normalize(forward + x * right + y * up_screen)
    far = 1.0e30
    eps = 1.0e-4 * scene_size

    # sky: a vertical gradient
    sky_t = wp.clamp(0.5 + 0.5 * wp.dot(d, up), 0.0, 1.0)
    sky = wp.lerp(wp.vec3(0.56, 0.58, 0.62), wp.vec3(0.30, 0.42, 0.62), sky_t)
    color = sky

    t_ground = far
    dn = wp.dot(d, up)
    eye_h = wp.dot(eye, up) - ground_height
    if ground_on != 0 and dn < 0.0 and eye_h > 0.0:
        t_ground = -eye_h / dn

    hit = wp.mesh_query_ray(mesh, eye, d, far)
    if hit.result and hit.t < t_ground:
        p = eye + hit.t * d
        f = hit.face
        idx = wp.mesh_get_index(mesh, 3 * f)
        jdx = wp.mesh_get_index(mesh, 3 * f + 1)
        kdx = wp.mesh_get_index(mesh, 3 * f + 2)
        n = hit.u * normals[idx] + hit.v * normals[jdx] + (1.0 - hit.u - hit.v) * normals[kdx]
        if wp.length_sq(n) > 0.0:
            n = wp.normalize(n)
        else:
            n = hit.normal
        if wp.dot(n, d) > 0.0:  # two-sided: back faces of open or self-intersecting surfaces
            n = -n
        albedo = body_colors[face_body[f]]
        lit = wp.max(wp.dot(n, light), 0.0)
        if lit > 0.0 and wp.mesh_query_ray(mesh, p + eps * n, light, far).result:
            lit = 0.0
        spec = wp.float32(0.0)
        if lit > 0.0:
            spec = 0.25 * wp.pow(wp.max(wp.dot(n, wp.normalize(light - d)), 0.0), 48.0)
        ambient = 0.22 + 0.14 * wp.dot(n, up)
        color = albedo * (ambient + 0.85 * lit) + wp.vec3(spec)
    elif t_ground < far:
        p = eye + t_ground * d
        footprint = t_ground * pixel_angle / wp.max(-dn, 0.05)
        half_width = 0.015 * grid_spacing
        line = wp.max(
            grid_line(wp.dot(p, ground_u), grid_spacing, half_width, footprint),
            grid_line(wp.dot(p, ground_v), grid_spacing, half_width, footprint),
        )
        base = wp.lerp(wp.vec3(0.62, 0.62, 0.60), wp.vec3(0.36, 0.36, 0.36), 0.6 * line)
        lit = wp.max(wp.dot(up, light), 0.0)
        p_up = p + eps * up
        if wp.mesh_query_ray(mesh, p_up, light, far).result:
            lit = 0.0
        contact = wp.mesh_query_ray(mesh, p_up, up, far)
        occlusion = 1.0
        if contact.result:
            occlusion = 1.0 - 0.55 * wp.exp(-contact.t / (0.08 * scene_size))
        ground = base * (0.35 * occlusion + 0.75 * lit)
        fog = 1.0 - wp.exp(-(t_ground / fog_distance) * (t_ground / fog_distance))
        color = wp.lerp(ground, sky, fog)

    image_out[i, j, 0] = to_byte(color[0])
    image_out[i, j, 1] = to_byte(color[1])
    image_out[i, j, 2] = to_byte(color[2])
