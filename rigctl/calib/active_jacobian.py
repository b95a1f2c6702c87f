"""The analytic Jacobian of the active-camera refinement's residuals.

The refinement (``active_refine``) predicts where a reference pixel ``p`` lands after a
head motion (thesis eq. 3.3, Lemma 3.1 with the parallax beyond it)::

    u0 = ((p - c) / f)                 normalised, distorted
    u  = D^-1(u0; k)                   undistorted (OpenCV's model D)
    m  = R^T ([u, 1] + s) - s          s = rho o (depths) or the held parallax
    xn = m_xy / m_z,  xd = D(xn; k),   pixel = f xd + c

Every step is differentiated in closed form, vectorised over all points, given the
motions' rotations and their derivatives (``active_refine.rotation_derivatives``). One
call costs about two evaluations of the residuals instead of one per parameter.
"""

from __future__ import annotations

import numpy as np

# the refinement's camera parameters: fx, fy, cx, cy, the mounting rotation (3), the roll
# axis (2), the parallax (3), then the distortion terms it estimates
N_BASE = 12


def _distortion_terms(x: np.ndarray, y: np.ndarray, k: np.ndarray, slots) -> tuple:
    """In one pass over normalised points (``x``, ``y``: each (N,)): OpenCV's distortion
    ``D`` (its x and y, as ``distort``; ``k`` = k1, k2, p1, p2, k3), its Jacobian
    ``dD/dxy`` (the entries J00, J01 = J10 and J11, each (N,)) and ``dD/dk`` of the terms
    in ``slots`` only (per slot its x and y rows, each (N,))."""
    k1, k2, p1, p2, k3 = k
    xx, yy, xy_ = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    xd = x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
    yd = y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
    d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    two_d = 2 * d_radial
    J00 = radial + two_d * xx + 2 * p1 * y + 6 * p2 * x
    J01 = two_d * xy_ + 2 * p1 * x + 2 * p2 * y
    J11 = radial + two_d * yy + 6 * p1 * y + 2 * p2 * x
    r4 = r2 * r2
    columns = {0: lambda: (x * r2, y * r2), 1: lambda: (x * r4, y * r4),
               2: lambda: (2 * xy_, r2 + 2 * yy), 3: lambda: (r2 + 2 * xx, 2 * xy_),
               4: lambda: (x * (r4 * r2), y * (r4 * r2))}
    return xd, yd, J00, J01, J11, [columns[slot]() for slot in slots]


def undistortion_terms(und_unique: np.ndarray, k: np.ndarray, dist_slots) -> np.ndarray:
    """At each distinct reference point (undistorted normalised ``und_unique``, (N, 2)),
    what ``residual_jacobian`` needs of the undistortion ``u = D^-1(u0)``, one row per
    quantity (N columns, so that one gather takes them all for every residual row):
    ``u0 = D(u)`` (x, y), the entries of ``du / du0 = Jd(u)^-1`` (A00, A01 = A10, A11)
    and ``dD/dk`` of the terms in ``dist_slots`` (x, y per term). Taken once per
    evaluation when the rows are split into chunks."""
    u0x, u0y, I00, I01, I11, Jk = _distortion_terms(und_unique[:, 0], und_unique[:, 1], k,
                                                    dist_slots)
    det = I00 * I11 - I01 * I01
    return np.array([u0x, u0y, I11 / det, -I01 / det, I00 / det,
                     *(row for pair in Jk for row in pair)])


def distortion_vector(x: np.ndarray, n_dist: int, dist_slots) -> np.ndarray:
    """OpenCV's five distortion terms (k1, k2, p1, p2, k3) from the camera parameters
    ``x``, zero where ``dist_slots`` estimates none."""
    k = np.zeros(5)
    k[list(dist_slots)] = x[N_BASE:N_BASE + n_dist]
    return k


def residual_jacobian(x: np.ndarray, n_dist: int, dist_slots: tuple, und_unique: np.ndarray,
                      point: np.ndarray, normals: np.ndarray, rotations: list[np.ndarray],
                      d_rotations: np.ndarray, counts: list[int], s: np.ndarray,
                      rho: np.ndarray | None, und_terms: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """d residual / d x over the camera parameters (rows, N_BASE + n_dist), with depths
    d residual / d rho of each row's own inverse depth (rows,), and each row's predicted
    pixel (rows, 2; the residual is its distance from the target along the normal). With the head
    angles' derivatives in ``d_rotations`` (11 per motion, ``rotation_derivatives(...,
    angles=True)``) six more columns follow: d residual / d (pan, tilt, roll) of the
    motion's first capture, then of its second. A residual is the
    predicted pixel's distance along ``normals`` (rows, 2) from its target (thesis eq. 3.3
    with the parallax, module docstring); a point correspondence is two rows, with the
    normals (1, 0) and (0, 1).

    ``und_unique``: the distinct reference points' undistorted normalised coordinates,
    ``point`` each row's index into them (every motion re-uses the reference image's
    contour points, so the undistortion's derivatives are taken once per point);
    ``rotations``, ``d_rotations``, ``counts``: per motion, its rotation, that rotation's
    derivatives (``active_refine.rotation_derivatives``) and how many consecutive rows it
    owns; ``s``: the parallax per row (rows, 3) or shared (3,); ``rho``: per row, or None
    when ``s`` is held (then x[9:12] is that ``s``). Rays are rows: a motion maps ``ray``
    to ``ray @ R - s``. Only the products with each motion's own rotation go motion by
    motion. ``und_terms``: ``undistortion_terms`` of ``und_unique``, when the caller
    took them once for several chunks of rows (else they are taken here).

    Every per-row quantity is held as a contiguous vector (a row of a (k, rows) array):
    numpy's loops over rows of three or twelve numbers cost more than the arithmetic
    (the same numbers to rounding; 135,000 rows of random world 11015 in one pass, 77 to
    55 ms)."""
    fx, fy = x[0], x[1]
    k = distortion_vector(x, n_dist, dist_slots)
    und_t = np.take(und_unique.T, point, axis=1)  # (2, rows)
    n = und_t.shape[1]
    s_t = s.T if s.ndim == 2 else s[:, None]
    rays_t = np.empty((3, n))
    rays_t[:2] = und_t + s_t[:2]
    rays_t[2] = 1.0 + s_t[2]
    bounds = np.cumsum([0, *counts])
    m_t = np.empty((3, n))
    for R, a, b in zip(rotations, bounds[:-1], bounds[1:], strict=True):
        np.matmul(R.T, rays_t[:, a:b], out=m_t[:, a:b])
    m_t -= s_t
    z = np.maximum(m_t[2], 1e-3)
    inv_z = 1 / z
    xn0, xn1 = m_t[0] / z, m_t[1] / z  # as ``active_refine._predict_all`` divides
    # d residual / d xn = n^T F Jd (Jd: the distortion's Jacobian at xn), then through
    # xn = m_xy / m_z
    normal0, normal1 = normals[:, 0], normals[:, 1]
    nf0, nf1 = normal0 * fx, normal1 * fy
    if n_dist:
        xd0, xd1, J00, J01, J11, Jk_out = _distortion_terms(xn0, xn1, k, dist_slots)
        g0 = nf0 * J00 + nf1 * J01
        g1 = nf0 * J01 + nf1 * J11
    else:
        xd0, xd1, g0, g1, Jk_out = xn0, xn1, nf0, nf1, []
    # [ray_j dr_dm_c for j, c] (9 rows) then dr_dm (3): per motion one product gives
    # d / d q for the rotation's parameters q (sum over j, c of ray_j dr_dm_c dR_q[j, c]),
    # d / d und (R's first two rows) and d / d s (R - I)
    n_rot = d_rotations[0].shape[0] if len(d_rotations) else 5  # 11: with the head angles
    terms_t = np.empty((12, n))
    dr_dm = terms_t[9:]
    np.multiply(g0, inv_z, out=dr_dm[0])
    np.multiply(g1, inv_z, out=dr_dm[1])
    np.multiply(-(g0 * xn0 + g1 * xn1), inv_z, out=dr_dm[2])
    for j in range(3):
        np.multiply(rays_t[j], dr_dm, out=terms_t[3 * j:3 * j + 3])
    n_cols = N_BASE + n_dist + n_rot - 5
    out_t = np.empty((n_cols, n))  # column-major: each parameter's column contiguous
    per_motion_t = np.empty((n_rot + 5, n))
    B = _motion_products(rotations, d_rotations, n_rot)
    for B_m, a, b in zip(B, bounds[:-1], bounds[1:], strict=True):
        np.matmul(B_m.T, terms_t[:, a:b], out=per_motion_t[:, a:b])
    out_t[4:9] = per_motion_t[:5]
    out_t[N_BASE + n_dist:] = per_motion_t[5:n_rot]
    du0, du1 = per_motion_t[n_rot], per_motion_t[n_rot + 1]
    dr_ds = per_motion_t[n_rot + 2:]
    # back through the undistortion u = D^-1(u0): du / du0 = Jd(u)^-1, at each distinct
    # reference point once
    if n_dist:
        table = und_terms if und_terms is not None else \
            undistortion_terms(und_unique, k, dist_slots)
        rows = np.take(table, point, axis=1)  # the inverse's entries etc., per row
        u0x, u0y, A00, A01, A11 = rows[:5]
        d0 = du0 * A00 + du1 * A01
        d1 = du0 * A01 + du1 * A11
    else:
        d0, d1 = du0, du1
        u0x, u0y = und_t
    # intrinsics: the direct term of pixel = f xd + c, and u0 = (p - c) / f before
    out_t[0] = normal0 * xd0 - d0 * u0x / fx
    out_t[1] = normal1 * xd1 - d1 * u0y / fy
    out_t[2] = normal0 - d0 / fx
    out_t[3] = normal1 - d1 / fy
    # the parallax: s = rho o (depths), or s itself when held
    if rho is not None:
        np.multiply(dr_ds, rho, out=out_t[9:12])
        d_rho = x[9] * dr_ds[0] + x[10] * dr_ds[1] + x[11] * dr_ds[2]
    else:
        out_t[9:12] = dr_ds
        d_rho = None
    # distortion: at the output point, and through the undistortion of the input
    for j, (kx_out, ky_out) in enumerate(Jk_out):
        kx_in, ky_in = rows[5 + 2 * j], rows[6 + 2 * j]
        out_t[N_BASE + j] = nf0 * kx_out + nf1 * ky_out - d0 * kx_in - d1 * ky_in
    pixels = np.empty((n, 2))
    pixels[:, 0] = fx * xd0 + x[2]
    pixels[:, 1] = fy * xd1 + x[3]
    return out_t.T, d_rho, pixels


def _motion_products(rotations, d_rotations, n_rot: int) -> np.ndarray:
    """Per motion (motions x 12 x (n_rot + 5)), the matrix ``B`` whose transpose takes
    a row's 12 terms of ``residual_jacobian`` (thesis eq. 3.3's residual, differentiated)
    to d residual / d (the rotation's parameters, und, s): ``B[:9, :n_rot]`` the
    derivatives of ``R`` flattened, ``B[9:, n_rot:n_rot + 2]`` its first two rows
    transposed, ``B[9:, n_rot + 2:]`` ``(R - I)^T``. Built for all motions at once
    (filled one motion at a time, a call at 3,327 rows and 31 motions took 3.10 ms
    instead of 2.94); each motion's ``B`` is laid out as before, so that its product
    is the same to the bit."""
    R = np.asarray(rotations, float).reshape(-1, 3, 3)
    dR = np.asarray(d_rotations, float).reshape(len(R), n_rot, 9)
    B = np.zeros((len(R), 12, n_rot + 5))
    B[:, :9, :n_rot] = dR.transpose(0, 2, 1)
    B[:, 9:, n_rot:n_rot + 2] = R[:, :2, :].transpose(0, 2, 1)
    B[:, 9:, n_rot + 2:] = (R - np.eye(3)).transpose(0, 2, 1)
    return B


def distort(xy: np.ndarray, k: np.ndarray) -> np.ndarray:
    """OpenCV's radial (k1, k2, k3) and tangential (p1, p2) model on normalised points
    (``k`` = k1, k2, p1, p2, k3)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    return np.stack([x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x),
                     y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y], axis=1)
