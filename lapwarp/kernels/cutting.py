"""Cutting kernels: tool activation, element removal by carving distance, tet surface re-extraction and
per-env connectivity (concurrent union-find) with per-label counters. See ``lapwarp.cutting`` and ``docs/cutting.md``.

Elements of a ``CuttingSystem`` are one flat list over its cuttable objects (tets, cloth triangles, rod
segments). Element ``e`` has up to four particles ``elem_nodes[e]`` (-1 padded), a kind (0 tet, 1 triangle,
2 segment) selecting which State mask holds it, and ``elem_col[e]``, its column in that mask.
"""

import warp as wp

from lapwarp.kernels.geometry import closest_segment_segment

wp.set_module_options({"enable_backward": False})

KIND_TET = wp.constant(0)
KIND_TRI = wp.constant(1)
KIND_SEG = wp.constant(2)


@wp.func
def element_alive(
    env: int,
    kind: int,
    col: int,
    tet_active: wp.array2d(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    segment_active: wp.array2d(dtype=wp.int32),
):
    if kind == KIND_TET:
        return tet_active[env, col]
    if kind == KIND_TRI:
        return tri_active[env, col]
    return segment_active[env, col]


@wp.func
def element_kill(
    env: int,
    kind: int,
    col: int,
    tet_active: wp.array2d(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    segment_active: wp.array2d(dtype=wp.int32),
):
    if kind == KIND_TET:
        tet_active[env, col] = 0
    elif kind == KIND_TRI:
        tri_active[env, col] = 0
    else:
        segment_active[env, col] = 0


@wp.func
def point_segment_distance(p: wp.vec3, a: wp.vec3, b: wp.vec3):
    ab = b - a
    den = wp.dot(ab, ab)
    t = float(0.0)
    if den > 0.0:
        t = wp.clamp(wp.dot(p - a, ab) / den, 0.0, 1.0)
    return wp.length(p - (a + ab * t))


# ----------------------------------------------------------------------------------------------------
# tool activation
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def hook_activation(activation: wp.array(dtype=float), deadzone: float, tool_active_out: wp.array(dtype=wp.int32)):
    """Electrocautery: the hook cuts while its activation action exceeds the dead zone (sofa_env: 0.1)."""
    env = wp.tid()
    a = int(0)
    if activation[env] > deadzone:
        a = 1
    tool_active_out[env] = a


@wp.kernel
def scissors_closing(
    angle: wp.array(dtype=float),
    min_closing: float,
    angle_prev: wp.array(dtype=float),
    tool_active_out: wp.array(dtype=wp.int32),
):
    """Scissors cut while their jaws close: the opening angle dropped by more than ``min_closing`` since the
    last call (then the previous angle is updated)."""
    env = wp.tid()
    a = angle[env]
    act = int(0)
    if angle_prev[env] - a > min_closing:
        act = 1
    tool_active_out[env] = act
    angle_prev[env] = a


# ----------------------------------------------------------------------------------------------------
# removal
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def cut_elements(
    elem_nodes: wp.array(dtype=wp.vec4i),
    elem_kind: wp.array(dtype=wp.int32),
    elem_col: wp.array(dtype=wp.int32),
    elem_label: wp.array(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    tool_a: wp.array2d(dtype=wp.vec3),
    tool_b: wp.array2d(dtype=wp.vec3),
    tool_radius: wp.array(dtype=float),
    tool_active: wp.array(dtype=wp.int32),
    carving_distance: float,
    tet_active: wp.array2d(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    segment_active: wp.array2d(dtype=wp.int32),
    removed: wp.array2d(dtype=wp.int32),
    cut_happened: wp.array(dtype=wp.int32),
    cut_dirty: wp.array2d(dtype=wp.int32),
):
    """Remove every live element within ``radius + carving_distance`` of a tool capsule: tets and triangles by their
    centroid, rod segments by their closest point (SOFA carves line models along their length; a rope's 5 mm
    segments would otherwise need the tool at their midpoint, where contact may never let it go)."""
    env, e = wp.tid()
    if tool_active[env] == 0:
        return  # most envs most steps: one load and out
    kind = elem_kind[e]
    col = elem_col[e]
    if element_alive(env, kind, col, tet_active, tri_active, segment_active) == 0:
        return
    nd = elem_nodes[e]
    c = q[env, nd[0]] + q[env, nd[1]]
    cnt = float(2.0)
    if nd[2] >= 0:
        c = c + q[env, nd[2]]
        cnt = 3.0
    if nd[3] >= 0:
        c = c + q[env, nd[3]]
        cnt = 4.0
    c = c / cnt
    hit = int(0)
    for k in range(tool_a.shape[1]):
        d = float(0.0)
        if kind == KIND_SEG:
            a = q[env, nd[0]]
            b = q[env, nd[1]]
            ta = tool_a[env, k]
            tb = tool_b[env, k]
            st = closest_segment_segment(a, b, ta, tb)
            d = wp.length((a + (b - a) * st[0]) - (ta + (tb - ta) * st[1]))
        else:
            d = point_segment_distance(c, tool_a[env, k], tool_b[env, k])
        if d <= tool_radius[k] + carving_distance:
            hit = 1
    if hit == 0:
        return
    element_kill(env, kind, col, tet_active, tri_active, segment_active)
    wp.atomic_add(removed, env, elem_label[e], 1)
    # benign races: every writer stores the same 1
    cut_happened[env] = 1
    cut_dirty[env, 0] = 1


# ----------------------------------------------------------------------------------------------------
# surfaces
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def tet_surface(
    cut_dirty: wp.array2d(dtype=wp.int32),
    tet_active: wp.array2d(dtype=wp.int32),
    face_neighbor: wp.array(dtype=wp.int32),
    face_active_out: wp.array2d(dtype=wp.int32),
):
    """Face 4 t + k is on the surface iff tet t is present and the tet across it is absent (or none)."""
    env, f = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    on = int(0)
    if tet_active[env, f / 4] != 0:
        nb = face_neighbor[f]
        on = 1
        if nb >= 0:
            if tet_active[env, nb] != 0:
                on = 0
    face_active_out[env, f] = on


@wp.kernel
def cloth_constraint_masks(
    cut_dirty: wp.array2d(dtype=wp.int32),
    edge_tris: wp.array(dtype=wp.vec2i),
    hinge_tris: wp.array(dtype=wp.vec2i),
    tri_active: wp.array2d(dtype=wp.int32),
    edge_active: wp.array2d(dtype=wp.int32),
    hinge_active: wp.array2d(dtype=wp.int32),
):
    """Edge and hinge masks of the envs whose triangles changed: an edge lives while one of its triangles does (a
    spring with no triangle, -1 -1, always), a hinge while both do. Once per cut, so the constraint kernels of every
    substep read one mask value instead of two triangle masks."""
    env, c = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    if c < edge_active.shape[1]:
        et = edge_tris[c]
        alive = int(1)
        if et[0] >= 0 or et[1] >= 0:
            alive = 0
            if et[0] >= 0:
                alive = tri_active[env, et[0]]
            if et[1] >= 0 and alive == 0:
                alive = tri_active[env, et[1]]
        edge_active[env, c] = alive
    if c < hinge_active.shape[1]:
        ht = hinge_tris[c]
        hinge_active[env, c] = wp.where(tri_active[env, ht[0]] != 0 and tri_active[env, ht[1]] != 0, 1, 0)


@wp.kernel
def particles_set_activity(
    elem_nodes: wp.array(dtype=wp.vec4i),
    elem_kind: wp.array(dtype=wp.int32),
    elem_col: wp.array(dtype=wp.int32),
    tet_active: wp.array2d(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    segment_active: wp.array2d(dtype=wp.int32),
    cut_dirty: wp.array2d(dtype=wp.int32),
    live_only: int,
    value: int,
    particle_active: wp.array2d(dtype=wp.int32),
):
    """Write ``value`` to the particles of the cuttable elements (of the live ones only with ``live_only``).

    Launched twice in order: clear every element's particles (live_only 0, value 0), then mark the particles of
    live elements (live_only 1, value 1), so a particle is active while one of its elements is. Races are benign:
    within a launch every writer stores the same value.
    """
    env, e = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    if live_only != 0:
        if element_alive(env, elem_kind[e], elem_col[e], tet_active, tri_active, segment_active) == 0:
            return
    nd = elem_nodes[e]
    for j in range(4):
        if nd[j] >= 0:
            particle_active[env, nd[j]] = value


# ----------------------------------------------------------------------------------------------------
# connectivity: concurrent union-find over (env, element) / (env, pair) threads, only for envs whose elements
# changed (cut_dirty). Five launches: init, hook (CAS), compress + count, label links, per-env tail.
# Invariant: component[env, x] <= x for every live x (a root is only ever hooked under a smaller element and
# path halving only moves a pointer to an ancestor), so every tree's root is its smallest element and any value
# read for a parent, even a stale one, is an ancestor. Hence the result equals the sequential union-find's.
# The flattening launch (conn_count) must not path-halve: there each slot is written by its own thread only.
# ----------------------------------------------------------------------------------------------------


@wp.func
def uf_find(parent: wp.array2d(dtype=wp.int32), env: int, x: int):
    r = x
    p = parent[env, r]
    while p != r:
        # path halving: every visited node skips to its grandparent (an ancestor: safe under concurrency)
        gp = parent[env, p]
        if gp != p:
            parent[env, r] = gp
        r = gp
        p = parent[env, r]
    return r


@wp.func
def uf_find_readonly(parent: wp.array2d(dtype=wp.int32), env: int, x: int):
    # no path halving: used while every thread flattens its own slot, so that slot has exactly one writer
    # (a halving store from another thread could overwrite a flattened root with an intermediate ancestor)
    r = x
    p = parent[env, r]
    while p != r:
        r = p
        p = parent[env, r]
    return r


@wp.kernel
def conn_init(
    elem_kind: wp.array(dtype=wp.int32),
    elem_col: wp.array(dtype=wp.int32),
    tet_active: wp.array2d(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    segment_active: wp.array2d(dtype=wp.int32),
    cut_dirty: wp.array2d(dtype=wp.int32),
    component: wp.array2d(dtype=wp.int32),
    root_bits: wp.array2d(dtype=wp.int32),
    num_components: wp.array2d(dtype=wp.int32),
    active_count: wp.array2d(dtype=wp.int32),
    label_links: wp.array2d(dtype=wp.int32),
):
    """Every live element its own component, removed ones -1; thread 0 of the env clears the counters."""
    env, e = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    if element_alive(env, elem_kind[e], elem_col[e], tet_active, tri_active, segment_active) != 0:
        component[env, e] = e
    else:
        component[env, e] = -1
    root_bits[env, e] = 0
    if e == 0:
        for o in range(num_components.shape[1]):
            num_components[env, o] = 0
        for la in range(active_count.shape[1]):
            active_count[env, la] = 0
        for k in range(label_links.shape[1]):
            label_links[env, k] = 0


@wp.kernel
def conn_hook(
    pairs: wp.array(dtype=wp.vec2i),
    cut_dirty: wp.array2d(dtype=wp.int32),
    component: wp.array2d(dtype=wp.int32),
):
    """Union the two live elements of pair ``p``: hook the larger root under the smaller one with a CAS."""
    env, p = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    ab = pairs[p]
    if component[env, ab[0]] < 0 or component[env, ab[1]] < 0:
        return
    ra = uf_find(component, env, ab[0])
    rb = uf_find(component, env, ab[1])
    while ra != rb:
        lo = wp.min(ra, rb)
        hi = wp.max(ra, rb)
        old = wp.atomic_cas(component, env, hi, hi, lo)
        if old == hi:
            break
        # hi was hooked meanwhile: continue from its (coherent) new parent, a smaller element
        nh = uf_find(component, env, old)
        if ra == hi:
            ra = nh
        else:
            rb = nh


@wp.kernel
def conn_count(
    elem_label: wp.array(dtype=wp.int32),
    elem_obj: wp.array(dtype=wp.int32),
    cut_dirty: wp.array2d(dtype=wp.int32),
    component: wp.array2d(dtype=wp.int32),
    root_bits: wp.array2d(dtype=wp.int32),
    num_components: wp.array2d(dtype=wp.int32),
    active_count: wp.array2d(dtype=wp.int32),
):
    """Flatten every live element to its root and count elements per label, labels per root, roots per object."""
    env, e = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    if component[env, e] < 0:
        return
    r = uf_find_readonly(component, env, e)
    component[env, e] = r
    lab = elem_label[e]
    wp.atomic_add(active_count, env, lab, 1)
    wp.atomic_or(root_bits, env, r, 1 << lab)
    if r == e:
        wp.atomic_add(num_components, env, elem_obj[e], 1)


@wp.kernel
def conn_links(
    cut_dirty: wp.array2d(dtype=wp.int32),
    root_bits: wp.array2d(dtype=wp.int32),
    label_links: wp.array2d(dtype=wp.int32),
):
    """label_links[la * L + lb] = 1 where one piece holds live elements of both labels (benign races: all store 1)."""
    env, e = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    bits = root_bits[env, e]
    if bits == 0:
        return
    L = int(0)
    while L * L < label_links.shape[1]:
        L += 1
    for la in range(L):
        if (bits >> la) & 1 != 0:
            for lb in range(L):
                if (bits >> lb) & 1 != 0:
                    label_links[env, la * L + lb] = 1


@wp.kernel
def conn_finish(
    label_total: wp.array(dtype=wp.int32),
    active_count: wp.array2d(dtype=wp.int32),
    cut_dirty: wp.array2d(dtype=wp.int32),
    cut_ratio: wp.array2d(dtype=float),
):
    """Cut ratio per label; clears ``cut_dirty`` (last launch of the update)."""
    env = wp.tid()
    if cut_dirty[env, 0] == 0:
        return
    for la in range(label_total.shape[0]):
        tot = label_total[la]
        ratio = float(0.0)
        if tot > 0:
            ratio = 1.0 - float(active_count[env, la]) / float(tot)
        cut_ratio[env, la] = ratio
    cut_dirty[env, 0] = 0
