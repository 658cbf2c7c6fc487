"""Plain NumPy reference implementations of the vision numba kernels, for tests to compare against."""

from __future__ import annotations

import cv2
import numpy as np

from appliance.background import (CELL_DARK_SHARE, CELL_PX, CORE_TOL, FLAT_CORE_SHARE, MAX_BRIGHT_SHARE,
                                  MIN_CELL_SHARE, MIN_CELLS, MIN_CORE_SHARE, MIN_DARK_SHARE, MIN_INNER_PX,
                                  MIN_TEXTURE, MIN_TEXTURE_NCC, NOISE, SHADOW_RATIO)
from appliance.grouping import (APART, FAR, LATE_BESIDE_K, LATE_BESIDE_M, LATE_BESIDE_X_M, LATE_HOST_K_SPREAD,
                                LATE_HOST_X_M, LINKED, MERGED_HI, MERGED_LO, MOVING, SETTLED_AGE, SLOW_REP_SHARE,
                                STANDING, UNSEEN)


def ncc_ref(img: np.ndarray, tmpl: np.ndarray, cx: int, cy: int) -> float:
    """NCC of a zero-mean unit-norm template with the patch centred at (cx, cy)."""
    h = tmpl.shape[0] // 2
    patch = img[cy - h : cy + h + 1, cx - h : cx + h + 1].astype(np.float64)
    z = patch - patch.mean()
    nrm = np.sqrt((z * z).sum())
    if nrm * nrm < 1e-6:
        return -1.0
    return float((z * tmpl).sum() / nrm)


def template_ref(img: np.ndarray, cx: int, cy: int, size: int) -> np.ndarray:
    h = size // 2
    patch = img[cy - h : cy + h + 1, cx - h : cx + h + 1].astype(np.float64)
    z = patch - patch.mean()
    return z / np.sqrt((z * z).sum())


def _parabola(a: float, b: float, c: float) -> float:
    d = a - 2.0 * b + c
    if d >= 0.0:
        return 0.0
    return float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))


def _project(M: np.ndarray, u: float, v: float) -> tuple[float, float]:
    q = M @ np.array([u, v, 1.0])
    return q[0] / q[2], q[1] / q[2]


def track_one_ref(img, Hm, Hinv, off, dt, s, P, tmpl, age, radius, ncc_min, q_acc, sigma_px, max_acc, max_lat):
    """One feature's predict/search/update. Returns (accepted, new s, new P, measured px, best ncc)
    or None when the search window leaves the image."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    G = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
    Q = q_acc**2 * G @ G.T
    sp = F @ s
    Pp = F @ P @ F.T + Q
    u, v = _project(Hinv, sp[0], sp[1])
    u += off[0]
    v += off[1]
    ua, va = _project(Hinv, sp[0] + np.sqrt(Pp[0, 0]), sp[1])
    ub, vb = _project(Hinv, sp[0], sp[1] + np.sqrt(Pp[1, 1]))
    sig_px = max(abs(ua + off[0] - u) + abs(va + off[1] - v), abs(ub + off[0] - u) + abs(vb + off[1] - v))
    r = min(radius if age >= 3 else radius + radius // 2, max(2, int(np.ceil(3.0 * sig_px + 1.0))))
    h = tmpl.shape[0] // 2
    cx, cy = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
    hh, ww = img.shape
    if cx - r - h - 1 < 0 or cy - r - h - 1 < 0 or cx + r + h + 1 >= ww or cy + r + h + 1 >= hh:
        return None
    scores = np.array([[ncc_ref(img, tmpl, cx + dx, cy + dy) for dx in range(-r, r + 1)] for dy in range(-r, r + 1)])
    by, bx = np.unravel_index(np.argmax(scores), scores.shape)
    best = scores[by, bx]
    if best < ncc_min:
        return False, sp, Pp, (u, v), best
    sx = _parabola(scores[by, bx - 1], best, scores[by, bx + 1]) if 0 < bx < 2 * r else 0.0
    sy = _parabola(scores[by - 1, bx], best, scores[by + 1, bx]) if 0 < by < 2 * r else 0.0
    mu, mv = cx + bx - r + sx, cy + by - r + sy
    z = np.array(_project(Hm, mu - off[0], mv - off[1]))
    J = np.array([
        np.array(_project(Hm, mu - off[0] + 1, mv - off[1])) - z,
        np.array(_project(Hm, mu - off[0], mv - off[1] + 1)) - z,
    ]).T
    R = sigma_px**2 * J @ J.T
    Hk = np.hstack([np.eye(2), np.zeros((2, 2))])
    S = Hk @ Pp @ Hk.T + R
    innov = z - sp[:2]
    slack = 0.5 * max_acc * dt * dt
    if np.any(np.abs(innov) > slack + 3 * np.sqrt(np.diag(S))):
        return False, sp, Pp, (u, v), best
    K = Pp @ Hk.T @ np.linalg.inv(S)
    sn = sp + K @ innov
    if abs(sn[2]) > max_lat:
        return False, sp, Pp, (u, v), best
    Pn = (np.eye(4) - K @ Hk) @ Pp
    return True, sn, Pn, (mu, mv), best


def select_spaced_ref(cand_xy: np.ndarray, live_xy: np.ndarray, spacing: float, max_n: int) -> list[int]:
    picked: list[int] = []
    for c, (x, y) in enumerate(cand_xy):
        if len(picked) >= max_n:
            break
        near_live = np.any((np.abs(live_xy[:, 0] - x) < spacing) & (np.abs(live_xy[:, 1] - y) < spacing)) if len(live_xy) else False
        near_pick = any(abs(cand_xy[k, 0] - x) < spacing and abs(cand_xy[k, 1] - y) < spacing for k in picked)
        if not near_live and not near_pick:
            picked.append(c)
    return picked


def pair_update_ref(live, s, lane, motion, state, rng, y0, conn_x, conn_y, seg_x, seg_y, seg_rel, late) -> None:
    """Same contract as grouping.pair_update, vectorised over the upper triangle."""
    live = np.sort(np.asarray(live))
    I, J = np.triu_indices(len(live), 1)
    i, j = live[I], live[J]
    dx = s[j, 0] - s[i, 0]
    dy = s[j, 1] - s[i, 1]
    st = state[i, j]
    new = st == UNSEEN
    near = (np.abs(dx) < conn_x) & (np.abs(dy) < conn_y)
    same = (lane[i] == lane[j]) & (lane[i] > 0) & (motion[i].astype(int) * motion[j] != STANDING * MOVING)
    state[i[new], j[new]] = np.where(same[new], np.where(near[new], LINKED, FAR), APART)
    link = (new & same & near) | ((st == FAR) & near & late[i] & late[j] & (motion[i] == MOVING)
                                  & (motion[j] == MOVING))
    state[i[link], j[link]] = LINKED
    for k, v in enumerate((dx, dx, dy, dy)):
        rng[i[link], j[link], k] = v[link]
    y0[i[link], j[link]] = s[i[link], 1]
    old = st == LINKED
    io, jo = i[old], j[old]
    r = rng[io, jo]
    r[:, 0] = np.minimum(r[:, 0], dx[old])
    r[:, 1] = np.maximum(r[:, 1], dx[old])
    r[:, 2] = np.minimum(r[:, 2], dy[old])
    r[:, 3] = np.maximum(r[:, 3], dy[old])
    rng[io, jo] = r
    travel = np.abs(s[io, 1] - y0[io, jo])
    apart = (r[:, 1] - r[:, 0] > seg_x) | (r[:, 3] - r[:, 2] > seg_y + seg_rel * travel)
    state[io[apart], jo[apart]] = APART


def components_ref(live, state) -> dict[int, int]:
    """slot -> its vehicle's label: breadth-first LINKED components, each with fragment features then joined
    to the component it is most MERGED with as the fragment (ties: the smallest slot); labelled by the
    smallest slot of what they form."""
    live = sorted(int(x) for x in live)

    def bfs(adj: dict[int, list[int]], nodes: list[int]) -> dict[int, int]:
        label: dict[int, int] = {}
        for i in nodes:
            if i in label:
                continue
            comp, todo = [], [i]
            while todo:
                k = todo.pop()
                if k not in label:
                    label[k] = -1
                    comp.append(k)
                    todo.extend(adj[k])
            for k in comp:
                label[k] = min(comp)
        return label

    adj: dict[int, list[int]] = {i: [] for i in live}
    for a, i in enumerate(live):
        for j in live[a + 1 :]:
            if state[i, j] == LINKED:
                adj[i] += [j]
                adj[j] += [i]
    part = bfs(adj, live)
    shared: dict[tuple[int, int], int] = {}
    for a, i in enumerate(live):
        for j in live[a + 1 :]:
            if state[i, j] in (MERGED_LO, MERGED_HI) and part[i] != part[j]:
                frag, host = (i, j) if state[i, j] == MERGED_LO else (j, i)
                key = (part[frag], part[host])
                shared[key] = shared.get(key, 0) + 1
    joined: dict[int, list[int]] = {c: [] for c in set(part.values())}
    for c in joined:
        hosts = {h: k for (f, h), k in shared.items() if f == c}
        if hosts:
            h = min(hosts, key=lambda q: (-hosts[q], q))
            joined[c] += [h]
            joined[h] += [c]
    top = bfs(joined, sorted(joined))
    return {i: top[part[i]] for i in live}


def assign_ids_ref(live, labels, fvid, next_vid, reported) -> tuple[dict[int, np.ndarray], int]:
    """vid -> member slots, biggest component first (ties: lower label), and the next free id: each component
    keeps its members' most frequent unclaimed reported id of which it holds most live features, else their
    most frequent unclaimed id (ties: the lower), else gets a new one. Updates fvid."""
    lab = labels[live]
    order = np.argsort(lab, kind="stable")
    sl, sv = lab[order], live[order]
    groups = np.split(sv, np.flatnonzero(np.diff(sl)) + 1)
    groups.sort(key=len, reverse=True)
    total = dict(zip(*(a.tolist() for a in np.unique(fvid[live], return_counts=True))))
    claimed: dict[int, np.ndarray] = {}
    for members in groups:
        vids = fvid[members]
        u, c = np.unique(vids[vids >= 0], return_counts=True)
        first = np.isin(u, reported) & (2 * c > np.array([total.get(int(v), 0) for v in u], dtype=np.int64))
        free = [k for k in np.lexsort((u, -c, ~first)) if int(u[k]) not in claimed]
        if free:
            vid = int(u[free[0]])
        else:
            vid, next_vid = next_vid, next_vid + 1
        fvid[members] = vid
        claimed[vid] = members
    return claimed, next_vid


def unbridge_ref(new, live, owner, s, state) -> np.ndarray:
    """Same contract as grouping.unbridge: per new feature, the vehicle (owner) of the LINKED owned feature
    nearest to it (city-block distance, the first in live order of equals), or -1; one linked to two vehicles
    or more is unlinked from every other vehicle's features (state changed in place, the new features in
    turn)."""
    def linked(i, j):
        return state[min(i, j), max(i, j)] == LINKED

    kept = np.full(len(new), -1)
    for a, i in enumerate(new):
        links = [j for j in live if j != i and owner[j] >= 0 and linked(i, j)]
        if not links:
            continue
        near = links[int(np.argmin([abs(s[j, 1] - s[i, 1]) + abs(s[j, 0] - s[i, 0]) for j in links]))]
        kept[a] = owner[near]
        if len({int(owner[j]) for j in links}) > 1:
            for j in links:
                if owner[j] != kept[a]:
                    state[min(i, j), max(i, j)] = APART
    return kept


def isolate_ref(new, kept, live, owner, state) -> None:
    """Same contract as grouping.isolate: each new feature keeps only its links to its own vehicle's
    features (none at all when kept gives it no vehicle)."""
    for i, keep in zip(new, kept):
        for j in live:
            if j != i and not (keep >= 0 and owner[j] == keep) and state[min(i, j), max(i, j)] == LINKED:
                state[min(i, j), max(i, j)] = APART


def fit_places_ref(members, age, s, fit, fit_vid, vid, d, cy, k_max, frames, min_var, neighbour) -> tuple:
    """Same contract as grouping.fit_places, vectorised over the group's features."""
    m = members[age[members] >= 3]
    stale = fit_vid[m] != vid
    fit[m[stale]] = 0.0
    fit_vid[m[stale]] = vid
    q = s[m, 1] - cy
    fit[m] += np.stack([np.ones_like(q), np.full_like(q, d), q, np.full_like(q, d * d), d * q], axis=1)
    f = fit[m]
    n = f[:, 0]
    var = f[:, 3] / n - (f[:, 1] / n) ** 2
    cov = f[:, 4] / n - f[:, 1] * f[:, 2] / (n * n)
    ok = (n >= frames) & (var >= min_var)
    if not ok.any() or q[~ok].max(initial=-np.inf) > q[ok].max():
        return float("nan"), float("nan")
    k = np.clip(cov[ok] / var[ok], 1.0, k_max)
    places = f[ok, 2] / n[ok] / k - f[ok, 1] / n[ok]
    order = np.argsort(places, kind="stable")
    places, k = places[order], k[order]
    close = np.flatnonzero(np.diff(places) <= neighbour)
    if len(close):
        return float(places[close[-1] + 1]), float(k[close[-1] + 1])
    h = len(places) // 2
    if len(places) % 2:
        return float(places[h]), float(k[h])
    return float((places[h - 1] + places[h]) / 2.0), float((k[h - 1] + k[h]) / 2.0)


def group_summary_ref(members, s, px, age, near_m, spot_m, moving, standing, fast, fast_min) -> tuple:
    """Same contract as grouping.group_summary, with NumPy on the group's features."""
    v = np.abs(s[members, 3])
    body = members
    if np.median(v) > moving and (v >= standing).any():
        body = members[v >= standing]
    settled = age[body] >= 3
    v_max = fast * np.median(np.abs(s[body[settled], 3])) if settled.sum() >= 4 else np.inf
    if v_max < fast * fast_min:
        v_max = np.inf
    v_med = np.median(s[body[settled], 3]) if settled.sum() >= 2 else 0.0
    slow = (age[body] < SETTLED_AGE) & (s[body, 3] * np.sign(v_med) < SLOW_REP_SHARE * abs(v_med)) \
        if abs(v_med) >= moving else np.zeros(len(body), np.bool_)
    not_fast = ~(settled & (np.abs(s[body, 3]) > v_max))
    ok = not_fast & ~slow
    cand = body[ok] if ok.any() else body[not_fast]
    rep = cand[np.argmax(px[cand, 1])] if len(cand) else body[0]
    ys = s[body, 1]
    low = body[np.abs(ys - s[rep, 1]) < near_m]
    near = low[age[low] >= 3]
    vx, vy = (np.median(s[near, 2]), np.median(s[near, 3])) if len(near) else (s[rep, 2], s[rep, 3])
    spot = near[np.abs(s[near, 1] - s[rep, 1]) < spot_m]
    vs = np.median(s[spot, 3]) if len(spot) else vy
    xs = s[low, 0]
    return body, rep, ys.max() - ys.min(), vx, vy, vs, np.median(xs), xs.min(), xs.max()


def alone_groups_ref(sl, sx, sy, sv, big, fx, fy, k_max) -> np.ndarray:
    """Same contract as grouping.alone_groups, vectorised over small groups x other groups."""
    bl, bx, by, bv, x_lo, x_hi, length, can = big.T
    with np.errstate(divide="ignore", invalid="ignore"):
        ol, ox, oy, ov = (np.concatenate(a) for a in ((sl, bl), (sx, bx), (sy, by), (sv, bv)))
        ratio = ov[None, :] / sv[:, None]
        beside = ((np.abs(ol[None, :] - sl[:, None]) == 1) & (np.abs(oy[None, :] - sy[:, None]) <= LATE_BESIDE_M)
                  & (np.abs(ox[None, :] - sx[:, None]) <= LATE_BESIDE_X_M)
                  & (ratio >= LATE_BESIDE_K[0]) & (ratio <= LATE_BESIDE_K[1])).any(axis=1)
        cand = (np.abs(sl[:, None] - bl[None, :]) <= 1) & (sv[:, None] * bv[None, :] > 0) & (can[None, :] != 0)
        k0 = sv[:, None] / bv[None, :]
        hosted = np.zeros(cand.shape, np.bool_)
        for spread in (1.0 - LATE_HOST_K_SPREAD, 1.0, 1.0 + LATE_HOST_K_SPREAD):
            k = np.clip(spread * k0, 1.0, k_max)
            gx, gy = fx + (sx[:, None] - fx) / k, fy + (sy[:, None] - fy) / k
            hosted |= ((gx >= x_lo - LATE_HOST_X_M) & (gx <= x_hi + LATE_HOST_X_M) & (gy >= by - 2.0)
                       & (gy <= by + 2.0 + length))
    return ~beside & ~(hosted & cand).any(axis=1)


def shadow_box_ref(img: np.ndarray, bg: np.ndarray, plain_ok: bool = True) -> bool:
    """appliance.background.shadow_box in NumPy (as Background.is_shadow was written before the kernel)."""
    a = img.astype(np.float32)
    b = bg.astype(np.float32)
    n = a.size
    if np.count_nonzero(a > b + NOISE) > MAX_BRIGHT_SHARE * n:
        return False
    dark = a < b - NOISE
    if np.count_nonzero(dark) < MIN_DARK_SHARE * n:
        return False
    rr = a[dark] / np.maximum(b[dark], 1.0)
    ratio = float(np.median(rr))
    if not SHADOW_RATIO[0] <= ratio <= SHADOW_RATIO[1]:
        return False
    if np.count_nonzero(np.abs(rr - ratio) <= CORE_TOL) < MIN_CORE_SHARE * len(rr):
        return False
    # The road's texture is compared cell by cell inside the dark area: a vehicle next to its own shadow
    # would pass a test over the whole box (the shadow's part correlates), its body's cells do not.
    nc, good = _cell_correlation(a, b, dark)
    if nc >= MIN_CELLS:
        return good >= MIN_CELL_SHARE * nc
    # too small for cells: the whole dark area away from its edges (penumbra, the caster's outline)
    inner = cv2.erode(dark.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    if np.count_nonzero(inner) < MIN_INNER_PX:
        inner = dark
    ai, bi = a[inner], b[inner]
    sb, sa = float(bi.std()), float(ai.std())
    if sb < MIN_TEXTURE:
        return plain_ok and np.count_nonzero(np.abs(ai / np.maximum(bi, 1.0) - ratio) <= CORE_TOL) >= \
            FLAT_CORE_SHARE * len(ai)
    if sa < 1e-3:
        return False
    ncc = float(np.mean((ai - ai.mean()) * (bi - bi.mean()))) / (sa * sb)
    return ncc >= MIN_TEXTURE_NCC


def _cell_correlation(a: np.ndarray, b: np.ndarray, dark: np.ndarray) -> tuple[int, int]:
    """(textured dark cells, those where image and road correlate) over CELL_PX square cells of a box."""
    c = CELL_PX
    ny, nx = a.shape[0] // c, a.shape[1] // c
    if ny == 0 or nx == 0:
        return 0, 0

    def cells(x: np.ndarray) -> np.ndarray:
        return x[:ny * c, :nx * c].reshape(ny, c, nx, c).swapaxes(1, 2).reshape(ny * nx, c * c)

    A, B = cells(a), cells(b)
    A = A - A.mean(axis=1, keepdims=True)
    B = B - B.mean(axis=1, keepdims=True)
    sa, sb = np.sqrt((A * A).mean(axis=1)), np.sqrt((B * B).mean(axis=1))
    ok = (cells(dark).mean(axis=1) >= CELL_DARK_SHARE) & (sb >= MIN_TEXTURE)
    ncc = (A[ok] * B[ok]).mean(axis=1) / np.maximum(sa[ok] * sb[ok], 1e-6)
    return int(ok.sum()), int(np.count_nonzero(ncc >= MIN_TEXTURE_NCC))
