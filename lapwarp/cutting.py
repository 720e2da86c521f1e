"""Element-mask cutting for a World: tools remove elements by clearing per-env ``active`` bits.

Cuttable objects are declared in the builder (``add_cloth / add_tet_mesh / add_rod(..., cuttable=True)``); the
World then carries State masks ``tet_active``, ``tri_active``, ``segment_active`` (1 = present), the per-env tet
surface ``tet_face_active`` and ``cut_dirty``. Constraint kernels skip removed elements, and ``World.reset(mask)``
restores masks, surfaces and the rest state of the masked envs only (they are ordinary State rows). Nothing is
ever reallocated, so a cut step is CUDA-graph capturable.

A :class:`CuttingSystem` is what a task drives once per env step, after ``world.step``::

    cut = CuttingSystem(world, carving_distance=1.2e-3, num_tools=2, num_labels=2)
    cut.add_object(cloth, labels=on_path.astype(int))      # per-element label (e.g. 1 = on the cutting path)
    cut.finalize()
    # each step: write the tool capsules (env frame) and whether the tool cuts, then
    cut.tool_a, cut.tool_b                                 # (num_envs, num_tools) wp.vec3, capsule axes
    cut.hook_activation(activation, deadzone=0.1)          # or cut.scissors_closing(jaw_angle)
    cut.cut()                                              # removal, surfaces, connectivity, counters

Outputs (device arrays, valid after ``cut()``):

* ``removed (N, L)``: elements removed by this call per label; ``cut_happened (N,)``.
* ``active_count (N, L)`` and ``cut_ratio (N, L)`` = 1 - present / initial elements of each label.
* ``num_components (N, objects)``: connected pieces of each object (a rope cut through: 2).
* ``label_links (N, L * L)``: 1 where some piece holds live elements of both labels (a flap still attached to
  its connective tissue); ``component (N, M)``: the piece (its smallest element) of each element, -1 = removed.

Removal rule: an element goes when it lies within ``tool_radius[k] + carving_distance`` of tool capsule ``k``
(segment ``tool_a`` -> ``tool_b``) while the env's ``tool_active`` is set: with ``removal="centroid"`` (the default)
a tet or triangle is measured at its centroid, with ``removal="touch"`` at its nearest point (a tet's nearest face),
which is what SOFA's CarvingManager does on a carved surface (its proximity query runs against the surface's
triangles, so a tool touching an element anywhere removes it), and with ``removal="vertex"`` at its vertices, what
the CarvingManager does on a carved point model (sofa_env's PrecisionCutting cloth: a point within reach is removed
with every triangle around it); rod segments are always measured at their nearest point. Connectivity
(union-find over the lanes of a thread block per env, only for envs where something was cut or that were reset)
joins tets across shared faces, triangles across shared edges, consecutive rod segments, plus links added with
:meth:`add_links`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.kernels import cutting as ck
from lapwarp.launching import make_struct

__all__ = ["CuttingSystem", "cut_surface"]


def cut_surface(world, obj) -> tuple[np.ndarray, wp.array]:
    """Faces of a cuttable object for rendering / export and their per-env active mask.

    Returns:
        ``(faces, face_active)``: faces ``(F, 3)`` int32 in the object's *local* particle indices and the
        ``(num_envs, F)`` int32 mask (a view of State, updated by ``CuttingSystem.cut`` and restored by reset).
        Cloth: its triangles and ``tri_active``. Tet mesh: all ``4 T`` tet faces and ``tet_face_active`` (faces of
        present tets with no present neighbour). Pass both to a ``VisualObject(face_active=...)``.
    """
    m, s = world.model, world.state
    if not obj.cuttable:
        raise ValueError(f"{obj.name!r} is not cuttable")
    if obj.kind == "cloth":
        a, b = obj.element_start, obj.element_start + len(obj.tris)
        faces = (obj.tris - obj.particle_start).astype(np.int32)
        mask = s.tri_active
    elif obj.kind == "tet_mesh":
        a, b = 4 * obj.element_start, 4 * (obj.element_start + len(obj.tets))
        faces = (m.tet_face_indices.numpy()[a:b] - obj.particle_start).astype(np.int32)
        mask = s.tet_face_active
    else:
        raise ValueError(f"{obj.kind} objects have no cut surface (rods render as tubes)")
    return faces, (mask if (a == 0 and b == mask.shape[1]) else mask[:, a:b])


class CuttingSystem:
    """Tools, cuttable elements and per-env cut counters of one World (see the module docstring).

    Args:
        world: a World built with at least one cuttable object.
        carving_distance: m, added to each tool radius (sofa_env: 1.2 mm hook, 0.2 mm scissors / dissection).
        num_tools: capsules per env (hook: a few segments along the hook; scissors: the blade between the jaws).
        num_labels: element labels (at most 32), e.g. off / on a cutting path, flap / connective tissue.
        tool_radius: scalar or ``(num_tools,)`` capsule radii, m.
        removal: ``"centroid"`` (a tet or triangle is measured at its centroid), ``"touch"`` (at its nearest point,
            SOFA's CarvingManager on a surface) or ``"vertex"`` (at its vertices, SOFA's CarvingManager on a point
            model); see the module docstring.
    """

    REMOVALS = ("centroid", "touch", "vertex")  # CutTools.removal: the index (kernels.cutting.REMOVAL_*)

    def __init__(self, world, carving_distance: float = 1.2e-3, num_tools: int = 1, num_labels: int = 1,
                 tool_radius=0.0, removal: str = "centroid"):
        if world.state.cut_dirty is None:
            raise ValueError("the World has no cuttable object (pass cuttable=True to the builder)")
        if not 1 <= num_labels <= 32:
            raise ValueError("num_labels must be in 1..32")
        if removal not in self.REMOVALS:
            raise ValueError(f"removal must be one of {self.REMOVALS}, got {removal!r}")
        self.removal = removal
        self.world = world
        # lanes of the per-env block of the cut-and-recount launch (CUDA): a changed env's phases stride its
        # elements over them; an unchanged env's block leaves at once
        self.block_threads = 128
        self.carving_distance = float(carving_distance)
        self.num_tools = int(num_tools)
        self.num_labels = int(num_labels)
        self._radius = np.broadcast_to(np.asarray(tool_radius, dtype=np.float32), (self.num_tools,)).copy()
        self._objects: list = []
        self._elems: list = []  # (nodes (m,4), kind, col (m,), label (m,), obj index)
        self._links: list = []
        self._finalized = False

    # ------------------------------------------------------------------------------------------------
    def add_object(self, obj, labels=None) -> int:
        """Make a cuttable object's elements cuttable by the tools; ``labels`` per element (default 0)."""
        if self._finalized:
            raise RuntimeError("CuttingSystem is finalized")
        if not obj.cuttable:
            raise ValueError(f"{obj.name!r} was not built with cuttable=True")
        m = self.world.model
        if obj.kind == "tet_mesh":
            nodes, kind, start = np.asarray(obj.tets), 0, obj.element_start
        elif obj.kind == "cloth":
            nodes, kind, start = np.concatenate([obj.tris, np.full((len(obj.tris), 1), -1)], axis=1), 1, \
                obj.element_start
        elif obj.kind == "rod":
            nodes = np.concatenate([obj.edges, np.full((len(obj.edges), 2), -1)], axis=1)
            kind, start = 2, obj.segment_start
        else:
            raise ValueError(f"{obj.kind} objects cannot be cut")
        n = len(nodes)
        lab = np.zeros(n, dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64).reshape(-1)
        if len(lab) != n or lab.min(initial=0) < 0 or lab.max(initial=0) >= self.num_labels:
            raise ValueError(f"labels must be {n} ints in [0, {self.num_labels})")
        oi = len(self._objects)
        self._objects.append(obj)
        self._elems.append((nodes.astype(np.int64), kind, np.arange(start, start + n), lab, oi))
        # adjacency inside the object (element indices local to the object for now)
        if kind == 0:
            nbr = m.tet_face_neighbor.numpy()[4 * start:4 * (start + n)] - start
            t = np.repeat(np.arange(n), 4)
            keep = (nbr >= 0) & (nbr < n) & (t < nbr)
            pairs = np.stack([t[keep], nbr[keep]], axis=1)
        elif kind == 1:
            et = m.edge_tris.numpy() - start
            keep = (et[:, 0] >= 0) & (et[:, 0] < n) & (et[:, 1] >= 0) & (et[:, 1] < n)
            pairs = et[keep]
        else:
            pairs = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
            if obj.closed and n > 2:
                pairs = np.concatenate([pairs, [[n - 1, 0]]])
        self._links.append((oi, pairs[:, 0], oi, pairs[:, 1]))
        return oi

    def add_links(self, obj_a: int, elems_a, obj_b: int, elems_b) -> None:
        """Count element ``elems_a[i]`` of object ``obj_a`` as connected to ``elems_b[i]`` of ``obj_b`` (indices
        returned by :meth:`add_object`; elements local to the object), e.g. a flap sewn to connective tissue."""
        a, b = np.asarray(elems_a).reshape(-1), np.asarray(elems_b).reshape(-1)
        if len(a) != len(b):
            raise ValueError("elems_a and elems_b differ in length")
        self._links.append((int(obj_a), a, int(obj_b), b))

    def finalize(self) -> CuttingSystem:
        """Allocate the device arrays (once)."""
        if not self._elems:
            raise ValueError("add at least one object")
        w, dev, N = self.world, self.world.device, self.world.num_envs
        offs = np.cumsum([0] + [len(e[0]) for e in self._elems])
        nodes = np.concatenate([e[0] for e in self._elems])
        kind = np.concatenate([np.full(len(e[0]), e[1]) for e in self._elems])
        col = np.concatenate([e[2] for e in self._elems])
        lab = np.concatenate([e[3] for e in self._elems])
        obj = np.concatenate([np.full(len(e[0]), e[4]) for e in self._elems])
        pairs = np.concatenate([np.stack([a + offs[oa], b + offs[ob]], axis=1) for oa, a, ob, b in self._links]
                               + [np.zeros((0, 2), dtype=np.int64)])
        self.num_elements = M = len(nodes)
        self.element_offsets = offs  # object i's elements are [offs[i], offs[i + 1]) of the system

        def arr(x, dtype):
            return wp.array(np.ascontiguousarray(x).astype(np.int32), dtype=dtype, device=dev)

        self._nodes = arr(nodes, wp.vec4i)
        self._kind = arr(kind, wp.int32)
        self._col = arr(col, wp.int32)
        self._label = arr(lab, wp.int32)
        self._obj = arr(obj, wp.int32)
        self._pairs = arr(pairs.reshape(-1, 2), wp.vec2i)
        self.label_total_host = np.bincount(lab, minlength=self.num_labels)
        self._label_total = arr(self.label_total_host, wp.int32)
        L, K = self.num_labels, self.num_tools
        self.tool_a = wp.zeros((N, K), dtype=wp.vec3, device=dev)
        self.tool_b = wp.zeros((N, K), dtype=wp.vec3, device=dev)
        self.tool_radius = wp.array(self._radius, dtype=float, device=dev)
        self.tool_active = wp.zeros(N, dtype=wp.int32, device=dev)
        self._angle_prev = wp.zeros(N, dtype=wp.float32, device=dev)
        self.removed = wp.zeros((N, L), dtype=wp.int32, device=dev)
        self.cut_happened = wp.zeros(N, dtype=wp.int32, device=dev)
        self.component = wp.zeros((N, M), dtype=wp.int32, device=dev)
        self._root_bits = wp.zeros((N, M), dtype=wp.int32, device=dev)
        self.num_components = wp.zeros((N, len(self._objects)), dtype=wp.int32, device=dev)
        self.active_count = wp.zeros((N, L), dtype=wp.int32, device=dev)
        self.cut_ratio = wp.zeros((N, L), dtype=float, device=dev)
        self.label_links = wp.zeros((N, L * L), dtype=wp.int32, device=dev)
        s, m = w.state, w.model
        none = wp.zeros((1, 0), dtype=wp.int32, device=dev)  # a mask this World does not carry: nothing to write
        no_pairs = wp.zeros(0, dtype=wp.vec2i, device=dev)

        def mask(a):
            return a if a is not None else none

        self._elements = make_struct(ck.CutElements, nodes=self._nodes, kind=self._kind, col=self._col,
                                     label=self._label, obj=self._obj, pairs=self._pairs, label_total=self._label_total)
        self._tools = make_struct(ck.CutTools, a=self.tool_a, b=self.tool_b, radius=self.tool_radius,
                                  active=self.tool_active, carving_distance=self.carving_distance,
                                  removal=self.REMOVALS.index(self.removal))
        self._mask_state = make_struct(
            ck.CutMaskState, tet_active=mask(s.tet_active), tri_active=mask(s.tri_active),
            segment_active=mask(s.segment_active), tet_face_active=mask(s.tet_face_active),
            edge_active=mask(s.edge_active), hinge_active=mask(s.hinge_active), particle_active=s.particle_active,
            tet_face_neighbor=m.tet_face_neighbor if m.tet_face_neighbor is not None else wp.zeros(0, dtype=wp.int32,
                                                                                                  device=dev),
            edge_tris=m.edge_tris if s.edge_active is not None else no_pairs,
            hinge_tris=m.hinge_tris if s.hinge_active is not None else no_pairs)
        self._counters = make_struct(ck.CutCounters, removed=self.removed, cut_happened=self.cut_happened,
                                     cut_dirty=s.cut_dirty, component=self.component, root_bits=self._root_bits,
                                     num_components=self.num_components, active_count=self.active_count,
                                     label_links=self.label_links, cut_ratio=self.cut_ratio)
        self._finalized = True
        self._launch(do_cut=0)  # initial connectivity / counters (cut_dirty starts at 1)
        return self

    # ------------------------------------------------------------------------------------------------
    def hook_activation(self, activation: wp.array, deadzone: float = 0.1) -> None:
        """``tool_active = activation > deadzone`` per env (electrocautery hook; ``activation`` ``(N,)`` float)."""
        launching.launch(ck.hook_activation, dim=self.world.num_envs, inputs=[activation, float(deadzone)],
                         outputs=[self.tool_active], device=self.world.device)

    def scissors_closing(self, jaw_angle: wp.array, min_closing: float = 0.0) -> None:
        """``tool_active`` = the jaw angle ``(N,)`` dropped by more than ``min_closing`` since the last call."""
        launching.launch(ck.scissors_closing, dim=self.world.num_envs, inputs=[jaw_angle, float(min_closing)],
                         outputs=[self._angle_prev, self.tool_active], device=self.world.device)

    def set_tools(self, a, b, active=None) -> None:
        """Host convenience: write tool capsule axes ``(N, K, 3)`` (or ``(K, 3)`` for all envs) and optionally the
        per-env ``active`` flags. Inside a captured step write ``tool_a`` / ``tool_b`` from kernels instead."""
        N, K = self.world.num_envs, self.num_tools
        self.tool_a.assign(np.ascontiguousarray(np.broadcast_to(np.asarray(a, np.float32), (N, K, 3))))
        self.tool_b.assign(np.ascontiguousarray(np.broadcast_to(np.asarray(b, np.float32), (N, K, 3))))
        if active is not None:
            self.tool_active.assign(np.broadcast_to(np.asarray(active, np.int32), (N,)).copy())

    def cut(self) -> None:
        """Remove elements touched by active tools, then refresh surfaces, connectivity and counters of the envs
        that changed (or were reset). One device launch: capturable."""
        self._launch(do_cut=1)

    def _launch(self, do_cut: int) -> None:
        # a thread block per env (ck.cut_and_recount); one lane per block on the CPU
        w = self.world
        if isinstance(self.block_threads, bool) or not isinstance(self.block_threads, int | np.integer) \
                or not 1 <= self.block_threads <= 1024:
            # 0 lanes would run nothing and leave every mask and counter as it was, silently
            raise ValueError(f"block_threads must be an int in [1, 1024] (lanes of one env's block), "
                             f"got {self.block_threads!r}")
        lanes = launching.block_lanes(w.device, self.block_threads)
        launching.launch(ck.cut_and_recount, dim=(w.num_envs, lanes),
                         inputs=[self._elements, self._tools, w.state.particle_q, int(do_cut)],
                         outputs=[self._mask_state, self._counters], device=w.device, block_dim=lanes)

    def refresh(self) -> None:
        """Recompute surfaces / connectivity / counters of envs restored by ``world.reset`` (cut_dirty = 1)
        without cutting; ``cut()`` does this too."""
        self._launch(do_cut=0)

    # host helpers (sync) ------------------------------------------------------------------------------
    def labels_connected(self, label_a: int, label_b: int) -> np.ndarray:
        """``(N,)`` bool: some piece holds live elements of both labels (host copy)."""
        L = self.num_labels
        return self.label_links.numpy()[:, label_a * L + label_b] != 0
