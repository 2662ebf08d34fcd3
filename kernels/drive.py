"""Driven motion: handles and moving colliders posed from rigid keyframes at the device's clock.

A track is a rigid motion given by keys (time in s, unit quaternion, translation in m) about a pivot,
interpolated linearly (rotations by slerp) and held before the first key and after the last, composed
with a rest pose: ``x(t) = pivot + T(t) + R(t) (R0 x + T0 - pivot)``. Each step, :func:`drive` poses the
moving colliders at the step's start and end and gives each held vertex the velocity that brings it to
its handle's pose at the step's end; :func:`tick` then advances the clock (ticks of a fixed share of a step,
so a frame of steps half as long keeps the motions' time), so a captured frame needs no host work.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated


@wp.struct
class Tracks:
    """Rigid motions: keys ``start[k]`` to ``start[k + 1]`` of track k, each track's pivot and rest pose."""

    start: wp.array(dtype=wp.int32)
    time: wp.array(dtype=float)
    rotation: wp.array(dtype=wp.quat)
    translation: wp.array(dtype=wp.vec3)
    pivot: wp.array(dtype=wp.vec3)
    rest_rotation: wp.array(dtype=wp.quat)
    rest_translation: wp.array(dtype=wp.vec3)


@wp.func
def track_pose(tracks: Tracks, k: int, t: float) -> wp.transform:
    """Track ``k``'s pose at time ``t`` (s): the transform taking rest coordinates to the world."""
    lo = tracks.start[k]
    hi = tracks.start[k + 1] - 1
    q = tracks.rotation[lo]
    move = tracks.translation[lo]
    if t >= tracks.time[hi]:
        q = tracks.rotation[hi]
        move = tracks.translation[hi]
    elif t > tracks.time[lo]:
        while hi - lo > 1:  # keys lo and hi bracket t
            mid = (lo + hi) // 2
            if tracks.time[mid] <= t:
                lo = mid
            else:
                hi = mid
        u = (t - tracks.time[lo]) / (tracks.time[hi] - tracks.time[lo])
        q = wp.quat_slerp(tracks.rotation[lo], tracks.rotation[hi], u)
        move = wp.lerp(tracks.translation[lo], tracks.translation[hi], u)
    pivot = tracks.pivot[k]
    rotation = q * tracks.rest_rotation[k]
    return wp.transform(pivot + move + wp.quat_rotate(q, tracks.rest_translation[k] - pivot), rotation)


@wp.kernel
def drive(
    clock: wp.array(dtype=wp.int32),
    tick_dt: float,
    dt: float,
    tracks: Tracks,
    collider_index: wp.array(dtype=wp.int32),
    collider_track: wp.array(dtype=wp.int32),
    held_vertex: wp.array(dtype=wp.int32),
    held_track: wp.array(dtype=wp.int32),
    rest_x: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    center_out: wp.array(dtype=wp.vec3),
    rotation_out: wp.array(dtype=wp.quat),
    center_next_out: wp.array(dtype=wp.vec3),
    rotation_next_out: wp.array(dtype=wp.quat),
    held_v_out: wp.array(dtype=wp.vec3),
):
    """Pose the moving colliders at the step's start and end, then the held vertices' velocities.

    The step starts ``clock`` ticks of ``tick_dt`` s in and lasts ``dt`` s. The first threads pose one collider
    each; the rest give each held vertex the velocity (m/s) that takes it from ``x`` to its handle's pose of its
    rest position at the step's end.
    """
    i = wp.tid()
    t = float(clock[0]) * tick_dt
    colliders = collider_index.shape[0]
    if i < colliders:
        o = collider_index[i]
        now = track_pose(tracks, collider_track[i], t)
        then = track_pose(tracks, collider_track[i], t + dt)
        center_out[o] = wp.transform_get_translation(now)
        rotation_out[o] = wp.transform_get_rotation(now)
        center_next_out[o] = wp.transform_get_translation(then)
        rotation_next_out[o] = wp.transform_get_rotation(then)
        return
    j = i - colliders
    vertex = held_vertex[j]
    target = wp.transform_point(track_pose(tracks, held_track[j], t + dt), rest_x[vertex])
    held_v_out[vertex] = (target - x[vertex]) / dt


@wp.kernel
def tick(clock: wp.array(dtype=wp.int32), ticks: int):
    """One step of ``ticks`` ticks taken: advance the clock."""
    clock[0] = clock[0] + ticks
