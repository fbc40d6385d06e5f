"""Exact geometric predicates in space: orient3d and insphere.

As in ``predicates.py`` (whose error-free transformations and expansions these reuse): the
determinant in floating point first, its sign returned when the value clears Shewchuk's
stage-A forward error bound, else the determinant again in exact expansion arithmetic. Never
compile with ``fastmath``. Exact while no intermediate product overflows or underflows
(coordinates zero or of magnitude in [1e-30, 1e30]; the engine's lie in [-1, 3)).

The points come as the rows of one array (a caller's scratch: no allocation on the fast
path). Conventions: ``orient3d(a, b, c, d)`` is the sign of det[a - d, b - d, c - d] (rows): +1 when
d lies on the side of the plane through a, b, c from which they turn clockwise (seen from
the other side they turn counter-clockwise), so orient3d((1, 0, 0), (0, 1, 0), (0, 0, 1),
(0, 0, 0)) = +1; 0 when the four are coplanar. ``insphere(a, b, c, d, e)`` is +1 when e lies
strictly inside the sphere through a, b, c, d for a tetrahedron with orient3d(a, b, c, d) >
0, -1 strictly outside, 0 on it; the sign is reversed for a negatively oriented tetrahedron
(``tests/test_predicates3.py`` pins both).
"""

import numpy as np

from .jit import kernel
from .predicates import EPS, diff_expansion, expansion_product, expansion_sign, expansion_sum

# Forward error bounds of the floating-point determinants (Shewchuk 1997, stage A).
O3D_ERRBOUND = (7.0 + 56.0 * EPS) * EPS
ISP_ERRBOUND = (16.0 + 224.0 * EPS) * EPS


@kernel()
def _negate(e, n):
    for i in range(n):
        e[i] = -e[i]


@kernel()
def _cross(px, npx, qy, nqy, qx, nqx, py, npy, out):
    """out = px * qy - qx * py (expansions); returns its length (out holds 16)."""
    t1 = np.empty(8)
    t2 = np.empty(8)
    n1 = expansion_product(px, npx, qy, nqy, t1)
    n2 = expansion_product(qx, nqx, py, npy, t2)
    _negate(t2, n2)
    return expansion_sum(t1, n1, t2, n2, out)


@kernel()
def _diffs(p, q, out):
    """out[a] = p[a] - q[a] for the three axes as expansions (rows of 2); lengths returned."""
    n = np.empty(3, np.int64)
    for a in range(3):
        n[a] = diff_expansion(p[a], q[a], out[a])
    return n


@kernel()
def _orient3d_exact(a, b, c, d):
    ad = np.empty((3, 2))
    bd = np.empty((3, 2))
    cd = np.empty((3, 2))
    na = _diffs(a, d, ad)
    nb = _diffs(b, d, bd)
    nc = _diffs(c, d, cd)
    # det = adx (bdy cdz - bdz cdy) + bdx (cdy adz - cdz ady) + cdx (ady bdz - adz bdy)
    m = np.empty(16)
    t = np.empty(64)
    acc = np.empty(192)
    tmp = np.empty(192)
    nm = _cross(bd[1], nb[1], cd[2], nc[2], bd[2], nb[2], cd[1], nc[1], m)
    nacc = expansion_product(ad[0], na[0], m, nm, acc)
    nm = _cross(cd[1], nc[1], ad[2], na[2], cd[2], nc[2], ad[1], na[1], m)
    nt = expansion_product(bd[0], nb[0], m, nm, t)
    nacc2 = expansion_sum(acc, nacc, t, nt, tmp)
    nm = _cross(ad[1], na[1], bd[2], nb[2], ad[2], na[2], bd[1], nb[1], m)
    nt = expansion_product(cd[0], nc[0], m, nm, t)
    nd = expansion_sum(tmp, nacc2, t, nt, acc)
    return expansion_sign(acc, nd)


@kernel()
def orient3d(p):
    """Sign of det[a - d, b - d, c - d] for the rows a, b, c, d of p (4, 3): module
    docstring."""
    a, b, c, d = p[0], p[1], p[2], p[3]
    adx, ady, adz = a[0] - d[0], a[1] - d[1], a[2] - d[2]
    bdx, bdy, bdz = b[0] - d[0], b[1] - d[1], b[2] - d[2]
    cdx, cdy, cdz = c[0] - d[0], c[1] - d[1], c[2] - d[2]
    bdxcdy = bdx * cdy
    cdxbdy = cdx * bdy
    cdxady = cdx * ady
    adxcdy = adx * cdy
    adxbdy = adx * bdy
    bdxady = bdx * ady
    det = adz * (bdxcdy - cdxbdy) + bdz * (cdxady - adxcdy) + cdz * (adxbdy - bdxady)
    permanent = (
        (abs(bdxcdy) + abs(cdxbdy)) * abs(adz)
        + (abs(cdxady) + abs(adxcdy)) * abs(bdz)
        + (abs(adxbdy) + abs(bdxady)) * abs(cdz)
    )
    bound = O3D_ERRBOUND * permanent
    if det > bound:
        return 1
    if -det > bound:
        return -1
    return _orient3d_exact(a, b, c, d)


@kernel()
def _lift(p, n, out):
    """out = p_x^2 + p_y^2 + p_z^2 (expansions); returns its length (out holds 24)."""
    sq = np.empty(8)
    two = np.empty(16)
    ns = expansion_product(p[0], n[0], p[0], n[0], sq)
    for i in range(ns):
        out[i] = sq[i]
    nl = ns
    for a in range(1, 3):
        ns = expansion_product(p[a], n[a], p[a], n[a], sq)
        nl = expansion_sum(out, nl, sq, ns, two)
        for i in range(nl):
            out[i] = two[i]
    return nl


@kernel()
def _triple(pz, npz, qr, nqr, qz, nqz, pr, npr, rz, nrz, pq, npq, out):
    """out = pz * qr - qz * pr + rz * pq (expansions: z's of 2, crosses of 16); returns its
    length (out holds 192)."""
    t = np.empty(64)
    u = np.empty(64)
    s = np.empty(128)
    nt = expansion_product(pz, npz, qr, nqr, t)
    nu = expansion_product(qz, nqz, pr, npr, u)
    _negate(u, nu)
    ns = expansion_sum(t, nt, u, nu, s)
    nt = expansion_product(rz, nrz, pq, npq, t)
    return expansion_sum(s, ns, t, nt, out)


@kernel()
def _insphere_exact(a, b, c, d, e):
    p = np.empty((4, 3, 2))
    n = np.empty((4, 3), np.int64)
    for i, q in enumerate((a, b, c, d)):
        ni = _diffs(q, e, p[i])
        for ax in range(3):  # not n[i] = ...: numba compiles its shape-mismatch message
            n[i, ax] = ni[ax]  # (string formatting) for an array assigned to a slice
    A, B, C, D = 0, 1, 2, 3
    cr = np.empty((6, 16))  # ab, bc, cd, da, ac, bd: x_i y_j - x_j y_i
    ncr = np.empty(6, np.int64)
    pairs = ((A, B), (B, C), (C, D), (D, A), (A, C), (B, D))
    for k in range(6):
        i, j = pairs[k]
        ncr[k] = _cross(p[i, 0], n[i, 0], p[j, 1], n[j, 1], p[j, 0], n[j, 0], p[i, 1], n[i, 1],
                        cr[k])  # fmt: skip
    AB, BC, CD, DA, AC, BD = 0, 1, 2, 3, 4, 5
    # abc = az bc - bz ac + cz ab;  bcd = bz cd - cz bd + dz bc
    # cda = cz da + dz ac + az cd;  dab = dz ab + az bd + bz da
    tri = np.empty((4, 192))
    ntri = np.empty(4, np.int64)
    ntri[0] = _triple(p[A, 2], n[A, 2], cr[BC], ncr[BC], p[B, 2], n[B, 2], cr[AC], ncr[AC],
                      p[C, 2], n[C, 2], cr[AB], ncr[AB], tri[0])  # fmt: skip
    ntri[1] = _triple(p[B, 2], n[B, 2], cr[CD], ncr[CD], p[C, 2], n[C, 2], cr[BD], ncr[BD],
                      p[D, 2], n[D, 2], cr[BC], ncr[BC], tri[1])  # fmt: skip
    neg_ac = cr[AC].copy()
    _negate(neg_ac, ncr[AC])
    ntri[2] = _triple(p[C, 2], n[C, 2], cr[DA], ncr[DA], p[D, 2], n[D, 2], neg_ac, ncr[AC],
                      p[A, 2], n[A, 2], cr[CD], ncr[CD], tri[2])  # fmt: skip
    neg_bd = cr[BD].copy()
    _negate(neg_bd, ncr[BD])
    ntri[3] = _triple(p[D, 2], n[D, 2], cr[AB], ncr[AB], p[A, 2], n[A, 2], neg_bd, ncr[BD],
                      p[B, 2], n[B, 2], cr[DA], ncr[DA], tri[3])  # fmt: skip
    # det = (dlift abc - clift dab) + (blift cda - alift bcd)
    lift = np.empty(24)
    term = np.empty(2 * 24 * 192)
    acc = np.empty(4 * 2 * 24 * 192)
    tmp = np.empty(4 * 2 * 24 * 192)
    nacc = 0
    order = ((D, 0, 1.0), (C, 3, -1.0), (B, 2, 1.0), (A, 1, -1.0))
    for k in range(4):
        who, t, sign = order[k]
        nl = _lift(p[who], n[who], lift)
        nt = expansion_product(lift, nl, tri[t], ntri[t], term)
        if sign < 0.0:
            _negate(term, nt)
        if nacc == 0:
            for i in range(nt):
                acc[i] = term[i]
            nacc = nt
        else:
            m = expansion_sum(acc, nacc, term, nt, tmp)
            for i in range(m):
                acc[i] = tmp[i]
            nacc = m
    return expansion_sign(acc, nacc)


@kernel()
def insphere(p):
    """For the rows a, b, c, d, e of p (5, 3): +1 if e lies strictly inside the sphere through
    a, b, c, d (orient3d > 0), -1 strictly outside, 0 on it; reversed for a negatively
    oriented tetrahedron."""
    a, b, c, d, e = p[0], p[1], p[2], p[3], p[4]
    aex, aey, aez = a[0] - e[0], a[1] - e[1], a[2] - e[2]
    bex, bey, bez = b[0] - e[0], b[1] - e[1], b[2] - e[2]
    cex, cey, cez = c[0] - e[0], c[1] - e[1], c[2] - e[2]
    dex, dey, dez = d[0] - e[0], d[1] - e[1], d[2] - e[2]
    aexbey = aex * bey
    bexaey = bex * aey
    ab = aexbey - bexaey
    bexcey = bex * cey
    cexbey = cex * bey
    bc = bexcey - cexbey
    cexdey = cex * dey
    dexcey = dex * cey
    cd = cexdey - dexcey
    dexaey = dex * aey
    aexdey = aex * dey
    da = dexaey - aexdey
    aexcey = aex * cey
    cexaey = cex * aey
    ac = aexcey - cexaey
    bexdey = bex * dey
    dexbey = dex * bey
    bd = bexdey - dexbey
    abc = aez * bc - bez * ac + cez * ab
    bcd = bez * cd - cez * bd + dez * bc
    cda = cez * da + dez * ac + aez * cd
    dab = dez * ab + aez * bd + bez * da
    alift = aex * aex + aey * aey + aez * aez
    blift = bex * bex + bey * bey + bez * bez
    clift = cex * cex + cey * cey + cez * cez
    dlift = dex * dex + dey * dey + dez * dez
    det = (dlift * abc - clift * dab) + (blift * cda - alift * bcd)
    # the same expression with every product's absolute value: bounds its rounding error
    abp = abs(aexbey) + abs(bexaey)
    bcp = abs(bexcey) + abs(cexbey)
    cdp = abs(cexdey) + abs(dexcey)
    dap = abs(dexaey) + abs(aexdey)
    acp = abs(aexcey) + abs(cexaey)
    bdp = abs(bexdey) + abs(dexbey)
    abcp = abs(aez) * bcp + abs(bez) * acp + abs(cez) * abp
    bcdp = abs(bez) * cdp + abs(cez) * bdp + abs(dez) * bcp
    cdap = abs(cez) * dap + abs(dez) * acp + abs(aez) * cdp
    dabp = abs(dez) * abp + abs(aez) * bdp + abs(bez) * dap
    permanent = (dlift * abcp + clift * dabp) + (blift * cdap + alift * bcdp)
    bound = ISP_ERRBOUND * permanent
    if det > bound:
        return 1
    if -det > bound:
        return -1
    return _insphere_exact(a, b, c, d, e)
