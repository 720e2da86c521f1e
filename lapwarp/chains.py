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
                    node_slots=len(node), lengths=np.asarray(edge_count))
