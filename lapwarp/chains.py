"""Chains of distance constraints for the direct solver (``lapwarp/kernels/chains.py``): host-side construction.

A *chain* is a path (or a loop) of distance constraints through consecutive nodes; the solver makes a whole chain
keep its lengths in one linear-time solve per sweep. A rod is one chain. A cloth's edges are split into straight
chains: at every vertex the incident edges that continue most nearly straight through it are paired (greedily by
the angle between them, at least ``min_angle_deg`` apart), and each edge is linked to its partner at each end. On a
regular grid this gives the rows, the columns and the diagonals; on an irregular mesh shorter chains, down to single
edges. Chains are then grouped into *families* of chains that share no node (a greedy colouring), so one launch
solves a family in parallel.

:class:`ChainSet` holds the flat arrays the kernel reads; ``SceneBuilder.finalize`` builds one for the rods and one
for the cloth edges.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp


@dataclass
class ChainSet:
    """Chains of one constraint group on the device (see the module docstring and ``kernels/chains.py``).

    Attributes:
        count: number of chains; ``edges``: number of constraints in all chains.
        edge_count, closed: ``(count,)`` int32 per chain, chains in family order.
        node: int32 global particle of every node slot, ``constraint``: int32 constraint index of every link slot;
            within a family link-major (link ``k`` of its ``i``-th chain at ``link_base + k * stride + i``, node
            ``j`` at ``node_base + j * stride + i``), padded to the family's longest chain.
        families: host list of ``(first chain, chains, link_base, node_base)``; the chains of one family share no node.
        link_slots, node_slots: sizes of the slot arrays (the per-env scratch has the same layout).
        lengths: host array of the chain lengths (links), for reports.
        closed_host, node_host, constraint_host: host copies of ``closed``, ``node`` and ``constraint`` (the block
            solve's packs are laid out from them, see :func:`pack_chains`).
    """

    count: int
    edges: int
    edge_count: wp.array
    closed: wp.array
    node: wp.array
    constraint: wp.array
    families: list = field(default_factory=list)
    link_slots: int = 0
    node_slots: int = 0
    lengths: np.ndarray | None = None
    closed_host: np.ndarray | None = None
    node_host: np.ndarray | None = None
    constraint_host: np.ndarray | None = None

    @property
    def num_families(self) -> int:
        return len(self.families)


def straight_chains(edges: np.ndarray, positions: np.ndarray, min_angle_deg: float = 120.0) -> list[tuple[list, list,
                                                                                                            bool]]:
    """Split an edge set into straight chains.

    Args:
        edges: ``(E, 2)`` node pairs.
        positions: ``(n, 3)`` rest positions of the nodes.
        min_angle_deg: two edges continue each other through a node only if the angle between them is at least this.

    Returns:
        ``[(nodes, edge_ids, closed), ...]``: node sequence (``len(edge_ids) + 1`` nodes, or ``len(edge_ids)`` for a
        closed loop) and the edges along it, every edge in exactly one chain.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    E = len(edges)
    link = -np.ones((E, 2), dtype=np.int64)  # partner edge at end 0 (node edges[e, 0]) and end 1
    cos_max = np.cos(np.radians(min_angle_deg))
    ends = np.concatenate([np.stack([np.arange(E), np.zeros(E, np.int64)], 1),
                           np.stack([np.arange(E), np.ones(E, np.int64)], 1)])
    node_of_end = edges[ends[:, 0], ends[:, 1]]
    other = edges[ends[:, 0], 1 - ends[:, 1]]
    d = positions[other] - positions[node_of_end]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    order = np.argsort(node_of_end, kind="stable")
    bounds = np.searchsorted(node_of_end[order], np.arange(len(positions) + 1))
    for v in range(len(positions)):
        inc = order[bounds[v]:bounds[v + 1]]  # end ids at node v
        if len(inc) < 2:
            continue
        dots = d[inc] @ d[inc].T
        iu, ju = np.triu_indices(len(inc), 1)
        cand = np.nonzero(dots[iu, ju] <= cos_max)[0]
        used = set()
        for k in cand[np.argsort(dots[iu[cand], ju[cand]], kind="stable")]:
            a, b = inc[iu[k]], inc[ju[k]]
            if a in used or b in used:
                continue
            used.update((a, b))
            link[ends[a, 0], ends[a, 1]] = ends[b, 0]
            link[ends[b, 0], ends[b, 1]] = ends[a, 0]

    seen = np.zeros(E, dtype=bool)
    chains = []

    def walk(e0: int, node0: int) -> tuple[list, list, bool]:
        nodes, ids = [node0], []
        e, node = e0, node0
        while True:
            seen[e] = True
            ids.append(int(e))
            end = 0 if edges[e, 0] == node else 1
            node = int(edges[e, 1 - end])
            nxt = link[e, 1 - end]
            if nxt < 0:
                nodes.append(node)
                return nodes, ids, False
            if nxt == e0:
                return nodes, ids, True  # back at the start: a loop (its first node is not repeated)
            nodes.append(node)
            e = int(nxt)

    for e in range(E):  # open chains start at an edge end with no partner
        if seen[e]:
            continue
        for end in (0, 1):
            if link[e, end] < 0:
                chains.append(walk(e, int(edges[e, end])))
                break
    for e in range(E):  # what is left are loops
        if not seen[e]:
            chains.append(walk(e, int(edges[e, 0])))
    return chains


def chain_families(chains: list[tuple[list, list, bool]], num_nodes: int) -> list[int]:
    """Greedy colouring: a family index per chain such that chains of one family share no node (longest first)."""
    colors_at: list[set] = [set() for _ in range(num_nodes)]
    family = [0] * len(chains)
    for c in sorted(range(len(chains)), key=lambda i: -len(chains[i][1])):
        taken = set().union(*(colors_at[v] for v in chains[c][0]))
        f = 0
        while f in taken:
            f += 1
        family[c] = f
        for v in chains[c][0]:
            colors_at[v].add(f)
    return family


def build_chain_set(chains: list[tuple[list, list, bool]], num_nodes: int, device) -> ChainSet:
    """Flatten chains (node lists in global particle indices, constraint ids) into a ``ChainSet``: chains grouped
    into families, each family's links and nodes interleaved link-major."""
    family = chain_families(chains, num_nodes)
    # by family, then longest first: the threads of a warp then walk chains of about the same length
    order = sorted(range(len(chains)), key=lambda c: (family[c], -len(chains[c][1]), c))
    edge_count = [len(chains[c][1]) for c in order]
    closed = [int(chains[c][2]) for c in order]
    node_slots, link_slots, families = [], [], []
    first = 0
    for f in sorted(set(family)):
        members = [c for c in order if family[c] == f]
        count, longest = len(members), max(len(chains[c][1]) for c in members)
        links = np.zeros((longest, count), dtype=np.int64)  # padding is never read (k < edge_count)
        nodes = np.zeros((longest + 1, count), dtype=np.int64)
        for i, c in enumerate(members):
            ids, chain_nodes = chains[c][1], chains[c][0]
            links[: len(ids), i] = ids
            nodes[: len(chain_nodes), i] = chain_nodes
        families.append((first, count, sum(a.size for a in link_slots), sum(a.size for a in node_slots)))
        link_slots.append(links.ravel())
        node_slots.append(nodes.ravel())
        first += count

    def arr(values):
        return wp.array(np.asarray(values, dtype=np.int32), dtype=wp.int32, device=device)

    link = np.concatenate(link_slots) if link_slots else np.zeros(0, np.int64)
    node = np.concatenate(node_slots) if node_slots else np.zeros(0, np.int64)
    return ChainSet(count=len(chains), edges=int(sum(edge_count)), edge_count=arr(edge_count), closed=arr(closed),
                    node=arr(node), constraint=arr(link), families=families, link_slots=len(link),
                    node_slots=len(node), lengths=np.asarray(edge_count), closed_host=np.asarray(closed, np.int32),
                    node_host=node.astype(np.int32), constraint_host=link.astype(np.int32))


@dataclass
class ChainPacks:
    """The chains of a :class:`ChainSet` packed into the thread blocks of the block (PCR) solve
    (``kernels/chains_block.py``), family by family.

    A pack is a run of consecutive chains of one family laid end to end as one row sequence: an open chain of ``m``
    links takes ``m + 1`` rows, row ``t`` holding node ``t`` and the link from it to node ``t + 1`` (the chain's last
    row has no link: an identity row of the link system, which with the zero couplings at the chain's ends keeps the
    chains of a pack independent, one tridiagonal system for all of them). A closed chain (a loop, solved in
    Sherman-Morrison form) takes a pack of its own, ``m`` rows.

    Attributes:
        rows: ``(R,)`` vec3i per row: (global particle of the node, constraint id of the link from it or -1, 1 where a
            chain starts); packs one after another.
        pack_start, pack_rows, pack_closed: ``(P,)`` int32 per pack: first row, row count, 1 for a loop.
        families: host list of ``(first pack, packs)``, in the chain set's family order.
        max_rows: the most rows of a pack (the kernel's shared tile length).
        capacity: the row budget the packs were laid out for.
        any_closed: whether some pack is a loop (host; the kernels compile their loop branches only then).
    """

    rows: wp.array
    pack_start: wp.array
    pack_rows: wp.array
    pack_closed: wp.array
    families: list
    max_rows: int
    capacity: int
    any_closed: bool = True


def pack_chains(cs: ChainSet, capacity: int, device) -> ChainPacks:
    """Pack each family's open chains, longest first, into runs of at most ``capacity`` rows (next fit; a chain
    longer than that alone); ``capacity <= 1``: one chain per pack. Host work from the chain set's host copies, once
    per layout."""
    rows, starts, counts, closed_flags, families = [], [], [], [], []
    total = 0  # rows so far: the packs' rows follow each other (a chain joins the last pack or opens one)
    for first, count, link_base, node_base in cs.families:
        pack_base = len(starts)
        current = None  # the open pack being filled: index into starts
        for i in range(count):
            r = first + i
            m = int(cs.lengths[r])
            loop = bool(cs.closed_host[r])
            n = m if loop else m + 1
            nodes = cs.node_host[node_base + i + count * np.arange(n)]
            links = np.full(n, -1, np.int32)
            links[:m] = cs.constraint_host[link_base + i + count * np.arange(m)]
            chain_rows = np.stack([nodes, links, np.zeros(n, np.int32)], 1)
            chain_rows[0, 2] = 1
            if loop or current is None or capacity <= 1 or counts[current] + n > capacity:
                starts.append(total)
                counts.append(0)
                closed_flags.append(int(loop))
                current = None if loop else len(starts) - 1
                target = len(starts) - 1
            else:
                target = current
            rows.append(chain_rows)
            counts[target] += n
            total += n
        families.append((pack_base, len(starts) - pack_base))
    flat = np.concatenate(rows).astype(np.int32) if rows else np.zeros((0, 3), np.int32)

    def arr(values, dtype=wp.int32):
        return wp.array(np.asarray(values, dtype=np.int32), dtype=dtype, device=device)

    return ChainPacks(rows=arr(flat, wp.vec3i), pack_start=arr(starts), pack_rows=arr(counts),
                      pack_closed=arr(closed_flags), families=families, max_rows=max(counts, default=1),
                      capacity=int(capacity), any_closed=any(closed_flags))
