"""Normalized median test and neighbour-median replacement on a vector grid, one thread a vector.

The field is an array3d of ``vec3`` (x, y, z components) indexed (z, y, x); NaN marks a missing
vector.
"""

from __future__ import annotations

import warp as wp

from lfcore.device import warp as _init

_init()
wp.set_module_options({"enable_backward": False})

vec26 = wp.types.vector(length=26, dtype=wp.float32)
NAN = wp.constant(float("nan"))


@wp.func
def median_of(v: vec26, n: int) -> float:
    """Median of the first n entries (insertion sort of a copy)."""
    for i in range(1, n):
        x = v[i]
        j = i - 1
        while j >= 0 and v[j] > x:
            v[j + 1] = v[j]
            j -= 1
        v[j + 1] = x
    return 0.5 * (v[(n - 1) // 2] + v[n // 2])


@wp.func
def axis_terms(i: int, n: int) -> wp.vec4:
    """(i0, w0, i1, w1): index i of an axis of n points as w0 f[i0] + w1 f[i1].

    Inside the grid f[i]; one step beyond an edge the point reflection about the edge vector,
    2 f[edge] - f[edge -+ 1]; w0 = 0 where there is nothing to reflect (an axis of one point).
    """
    if i >= 0 and i < n:
        return wp.vec4(float(i), 1.0, 0.0, 0.0)
    if n < 2:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    if i < 0:
        return wp.vec4(0.0, 2.0, 1.0, -1.0)
    return wp.vec4(float(n - 1), 2.0, float(n - 2), -1.0)


@wp.func
def reflected(field: wp.array3d(dtype=wp.vec3), z: int, y: int, x: int) -> wp.vec3:
    """The vector at (z, y, x), continued by point reflection up to one step past the edges."""
    if z >= 0 and y >= 0 and x >= 0 and z < field.shape[0] and y < field.shape[1] and x < field.shape[2]:
        return field[z, y, x]
    tz = axis_terms(z, field.shape[0])
    ty = axis_terms(y, field.shape[1])
    tx = axis_terms(x, field.shape[2])
    if tz[1] == 0.0 or ty[1] == 0.0 or tx[1] == 0.0:
        return wp.vec3(NAN, NAN, NAN)
    acc = wp.vec3(0.0, 0.0, 0.0)
    for a in range(2):
        wz = tz[2 * a + 1]
        if wz != 0.0:
            for b in range(2):
                wy = ty[2 * b + 1]
                if wy != 0.0:
                    for d in range(2):
                        wx = tx[2 * d + 1]
                        if wx != 0.0:
                            acc += wz * wy * wx * field[int(tz[2 * a]), int(ty[2 * b]), int(tx[2 * d])]
    return acc


@wp.kernel
def median_test(field: wp.array3d(dtype=wp.vec3), epsilon: float, threshold: float,
                outlier: wp.array3d(dtype=wp.int32)):
    """1 where |u - median| / (median residual + epsilon) > threshold for any component, or u is NaN."""
    z, y, x = wp.tid()
    u = field[z, y, x]
    bad = int(0)  # noqa: UP018 - a dynamic Warp variable
    if wp.isnan(u[0]) or wp.isnan(u[1]) or wp.isnan(u[2]):
        bad = 1
    else:
        vx = vec26()
        vy = vec26()
        vz = vec26()
        n = int(0)  # noqa: UP018 - a dynamic Warp variable
        for o in range(27):
            if o != 13:
                val = reflected(field, z + o // 9 - 1, y + (o // 3) % 3 - 1, x + o % 3 - 1)
                if not (wp.isnan(val[0]) or wp.isnan(val[1]) or wp.isnan(val[2])):
                    vx[n] = val[0]
                    vy[n] = val[1]
                    vz[n] = val[2]
                    n += 1
        if n > 0:
            for c in range(3):
                v = vx
                if c == 1:
                    v = vy
                elif c == 2:
                    v = vz
                med = median_of(v, n)
                r = vec26()
                for i in range(n):
                    r[i] = wp.abs(v[i] - med)
                if wp.abs(u[c] - med) / (median_of(r, n) + epsilon) > threshold:
                    bad = 1
    outlier[z, y, x] = bad


@wp.kernel
def replace_sweep(field: wp.array3d(dtype=wp.vec3), bad: wp.array3d(dtype=wp.int32), out: wp.array3d(dtype=wp.vec3),
                  filled: wp.array3d(dtype=wp.int32)):
    """One sweep: each bad vector becomes the median of its valid neighbours inside the grid, if any."""
    z, y, x = wp.tid()
    u = field[z, y, x]
    done = int(0)  # noqa: UP018 - a dynamic Warp variable
    if bad[z, y, x] != 0:
        m = wp.vec3(NAN, NAN, NAN)
        for c in range(3):
            v = vec26()
            n = int(0)  # noqa: UP018 - a dynamic Warp variable
            for o in range(27):
                k = z + o // 9 - 1
                j = y + (o // 3) % 3 - 1
                i = x + o % 3 - 1
                if (o != 13 and k >= 0 and j >= 0 and i >= 0 and k < field.shape[0] and j < field.shape[1]
                        and i < field.shape[2]):
                    if bad[k, j, i] == 0:
                        val = field[k, j, i][c]
                        if not wp.isnan(val):
                            v[n] = val
                            n += 1
            if n > 0:
                m[c] = median_of(v, n)
        if not (wp.isnan(m[0]) or wp.isnan(m[1]) or wp.isnan(m[2])):
            u = m
            done = 1
    out[z, y, x] = u
    filled[z, y, x] = done
