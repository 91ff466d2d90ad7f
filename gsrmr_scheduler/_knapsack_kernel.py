"""Numba kernel of the exact solver's dynamic programming (:mod:`gsrmr_scheduler.exact`).

States ``(W, ΔV, node)`` are kept sorted by W with strictly increasing ΔV (Pareto); ``node`` indexes a pool of
(item toggled, parent node) records, so the incumbent's toggles are recovered by following parents to node 0.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _lp(W: float, V: float, cap: float, e_rm: float, e_add: float) -> float:
    slack = cap - W
    if slack >= 0:
        return V + slack * e_add
    if math.isinf(e_rm):
        return -math.inf
    return V + slack * e_rm


@numba.njit(cache=True)
def _bound(W: float, V: float, cap: float, w: np.ndarray, v: np.ndarray, e: np.ndarray, s: int, t: int,
           wmin_t: float) -> float:
    n = e.size
    e_s = e[s] if s >= 0 else math.inf
    e_s1 = e[s - 1] if s >= 1 else math.inf
    e_t = e[t] if t < n else 0.0
    e_t1 = e[t + 1] if t + 1 < n else 0.0
    if cap >= W:
        if t >= n:
            return V
        b = max(_lp(W, V, cap, e_s, e_t1), _lp(W + w[t], V + v[t], cap, e_s, e_t1))
        su = cap - W
        if su < wmin_t and not math.isinf(e_s):
            tight = V + max(0.0, (e_t - e_s) * wmin_t + e_s * su)
            b = min(b, tight)
        return b
    if s < 0:
        return -math.inf
    return max(_lp(W, V, cap, e_s1, e_t), _lp(W - w[s], V - v[s], cap, e_s1, e_t))


@numba.njit(cache=True)
def dp_chunk(w, v, e, wmin, cap, tol, Ws, Vs, Ns, s, t, step, z, z_node, pool_j, pool_p, pool_n,
             max_steps, max_states):
    """Run up to ``max_steps`` core steps. Returns the updated state; ``status`` 0 = running,
    1 = finished (no live state or no item left), 2 = state limit."""
    n = e.size
    status = 0
    for _ in range(max_steps):
        m = Ws.size
        if m == 0 or (s < 0 and t >= n):
            status = 1
            break
        if t < n and (s < 0 or step % 2 == 0):
            j = t
            dw = w[t]
            dv = v[t]
            t += 1
        else:
            j = s
            dw = -w[s]
            dv = -v[s]
            s -= 1
        # Merge the two W-sorted lists (old, toggled) with Pareto filtering.
        Wn = np.empty(2 * m)
        Vn = np.empty(2 * m)
        Nn = np.empty(2 * m, dtype=np.int64)
        i0 = 0
        i1 = 0
        k = 0
        best = -math.inf
        while i0 < m or i1 < m:
            take_old = False
            if i1 >= m:
                take_old = True
            elif i0 < m:
                wa = Ws[i0]
                wb = Ws[i1] + dw
                if wa < wb or (wa == wb and Vs[i0] >= Vs[i1] + dv):
                    take_old = True
            if take_old:
                Wc = Ws[i0]
                Vc = Vs[i0]
                if Vc > best:
                    Wn[k] = Wc
                    Vn[k] = Vc
                    Nn[k] = Ns[i0]
                    k += 1
                    best = Vc
                i0 += 1
            else:
                Wc = Ws[i1] + dw
                Vc = Vs[i1] + dv
                if Vc > best:
                    if pool_n >= pool_j.size:
                        nj = np.empty(2 * pool_j.size, dtype=np.int64)
                        npp = np.empty(2 * pool_j.size, dtype=np.int64)
                        nj[:pool_n] = pool_j[:pool_n]
                        npp[:pool_n] = pool_p[:pool_n]
                        pool_j = nj
                        pool_p = npp
                    pool_j[pool_n] = j
                    pool_p[pool_n] = Ns[i1]
                    Wn[k] = Wc
                    Vn[k] = Vc
                    Nn[k] = pool_n
                    pool_n += 1
                    k += 1
                    best = Vc
                i1 += 1
        # Incumbent update, then fathoming.
        for i in range(k):
            if Wn[i] <= cap and Vn[i] > z:
                z = Vn[i]
                z_node = Nn[i]
        wmin_t = wmin[t] if t < n else math.inf
        live = 0
        for i in range(k):
            u = _bound(Wn[i], Vn[i], cap, w, v, e, s, t, wmin_t)
            if u > z + tol:
                Wn[live] = Wn[i]
                Vn[live] = Vn[i]
                Nn[live] = Nn[i]
                live += 1
        Ws = Wn[:live].copy()
        Vs = Vn[:live].copy()
        Ns = Nn[:live].copy()
        step += 1
        if live > max_states:
            status = 2
            break
    if status == 0 and (Ws.size == 0 or (s < 0 and t >= n)):
        status = 1
    return Ws, Vs, Ns, s, t, step, z, z_node, pool_j, pool_p, pool_n, status


@numba.njit(cache=True)
def max_bound(w, v, e, wmin, cap, Ws, Vs, s, t):
    """Largest bound over the live states (for the certified gap when stopped early)."""
    n = e.size
    wmin_t = wmin[t] if t < n else math.inf
    out = -math.inf
    for i in range(Ws.size):
        out = max(out, _bound(Ws[i], Vs[i], cap, w, v, e, s, t, wmin_t))
    return out
