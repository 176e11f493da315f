"""Conv ``feast``: FeaStNet (Verma et al. 2018, "FeaStNet: Feature-Steered Graph Convolutions
for 3D Shape Analysis"; thesis 3.3), with the parameters of ``torch_geometric.nn.FeaStConv``.

    x'_i = b + sum_{j in N(i) u {i}} 1/|N(i) u {i}| sum_{h=1}^{H} q_h(x_i, x_j) W_h x_j,
    q_h(x_i, x_j) = softmax_h(u_h^T (x_j - x_i) + c_h)

so the assignment of neighbours to the H weight matrices is steered by the features
themselves. The parameters are those of a ``FeaStConv`` held as ``self.conv`` (it draws them,
so seeded runs start from the weights torch_geometric gives, and its checkpoints load), but the
sums are evaluated in another order (``FeaStConv`` computes W x_j per *edge*, E H c_out floats
with E about 7 n b):

* ``aggregate``: T_ih = sum_j q_h(i, j) x_j / |N(i)| per edge (H c_in multiply-adds an edge),
  then one product x'_i = b + [T_i1 .. T_iH] [W_1 .. W_H]^T per vertex;
* ``transform``: Z_jh = W_h x_j once per vertex, then x'_i = b + sum_j sum_h q_h(i, j) Z_jh /
  |N(i)| per edge (H c_out an edge);

``auto`` takes ``transform`` where H c_out < c_in, else ``aggregate``: the per-edge width (the
floats gathered, c_in + H against H (c_out + 1), and the per-row products) sets the time more
than the multiply-adds (measured at 32 -> 16 channels, 8 heads: ``transform`` has half the
per-edge multiply-adds and was no faster). The steering logits u_h^T (x_j - x_i) + c_h =
(U x)_j - (U x)_i + c_h come from one product U x per vertex, their softmax from per-vertex
factors (``factors``: no exp per edge). Vertices are grouped by |N(i) u {i}| (no padding), activations are vertex-major
((n, b, c) in memory), and each group is evaluated a chunk of about ``CHUNK_BYTES`` of gathered
rows at a time by a custom autograd Function whose backward gathers and recomputes the chunk
instead of keeping the (E b, H c) intermediates; with T torch threads the chunks go to T
workers. Pooling is fused (``fuses_pooling``): ``forward(x, rows=kept)`` computes only the kept
vertices, ``forward_up(x, U)`` = forward(U x) with the per-vertex products taken on the coarse
vertices (``transform``: U (x W^T) and U (x U_s^T), both linear in x). Under autocast the conv
computes in float32 (the steering softmax is not left to bfloat16).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.autograd.function import once_differentiable

from fwk.errors import RecipeError
from fwk.graph import edge_index, sparse_apply
from fwk.hookspecs import hookimpl
from fwk.parallel import in_workers
from fwk.protocols import CONV_BUILD_ARGS

CHUNK_BYTES = 2 << 20  # gathered floats per chunk: about 2 MB (L2 is 1 MB a core, L3 32 MB)


class Plan:
    """The output vertices grouped by neighbourhood size K = |N(i) u {i}|, cut into chunks.

    ``groups``: per group (K, centre (m,) input-vertex index, out (m,) output position,
    nbr (m, K) input-vertex indices, the centre among them, edge multiplicities as in the edge
    list). ``chunks``: (group, start, stop) in group order, each gathering about ``CHUNK_BYTES``
    for ``width`` floats a neighbour and ``b`` samples; ``work``: the chunks of each worker.
    ``flat``, ``ctr``: per group, the rows of a vertex-major (n b, .) tensor that a chunk
    gathers ((vertex, sample, k) order) and its centres' rows; outputs are computed in plan
    order (``base``: each group's first output) and put in vertex order at the end;
    ``p_at``: per group, where its steering weights (m b K H) start in one flat buffer."""

    def __init__(self, groups, n_out, b, width, threads, heads):
        self.groups, self.n_out, self.b = groups, n_out, b
        chunks = []
        for g, (K, centre, _, _) in enumerate(groups):
            rows = max(1, CHUNK_BYTES // (4 * K * b * max(1, width)))
            m = len(centre)
            rows = max(1, min(rows, -(-m // max(1, threads))))
            chunks += [(g, s, min(m, s + rows)) for s in range(0, m, rows)]
        self.chunks = chunks
        self.workers = max(1, min(threads, len(chunks)))
        self.work = [chunks[w::self.workers] for w in range(self.workers)]
        self.flat, self.ctr, self.base, self.p_at = [], [], [], []
        at = base = 0
        for K, centre, out, nbr in groups:
            ar = torch.arange(b, device=nbr.device)
            self.flat.append((nbr[:, None, :] * b + ar[None, :, None]).reshape(-1))
            self.ctr.append((centre[:, None] * b + ar[None, :]).reshape(-1))
            self.base.append(base)
            self.p_at.append(at)
            base += len(centre)
            at += len(centre) * b * K * heads
        self.p_size = at
        # outputs are written in plan order (group by group: contiguous slices) and put in vertex
        # order by one gather at the end: `order` (n_out,) the plan position of each output
        dev = groups[0][1].device if groups else None
        perm = torch.cat([out for _, _, out, _ in groups]) if groups else torch.zeros(0, dtype=torch.long)
        self.perm = perm
        self.order = torch.empty_like(perm)
        self.order[perm] = torch.arange(len(perm), device=dev)

    def rows(self, g, s0, s1):
        """(K, kb, flat, ctr, (a, z)) of chunk [s0, s1) of group g; rows [a, z) of the plan-order
        (n_out b, .) output."""
        K, b, base = self.groups[g][0], self.b, self.base[g]
        return (K, (s1 - s0) * b, self.flat[g][s0 * b * K:s1 * b * K], self.ctr[g][s0 * b:s1 * b],
                ((base + s0) * b, (base + s1) * b))

    def to_vertex_order(self, y):
        """(n_out b, c) in plan order -> (n_out, b, c) in output order."""
        return y.view(self.n_out, self.b, -1).index_select(0, self.order)

    def to_plan_order(self, gy):
        """(n_out b, c) in output order -> (n_out b, c) in plan order (contiguous)."""
        return gy.view(self.n_out, -1).index_select(0, self.perm).view(self.n_out * self.b, -1)

    def p_slice(self, P, g, s0, s1, H):
        """The chunk's steering weights in the flat buffer P, as (kb, K, H)."""
        K, b = self.groups[g][0], self.b
        a = self.p_at[g] + s0 * b * K * H
        return P[a:a + (s1 - s0) * b * K * H].view(-1, K, H)


def neighbourhoods(ei: torch.Tensor, n: int):
    """Per target vertex i, the sources j of the edges j -> i of ``ei`` (2, E) with self loops
    removed and one added, as torch_geometric's FeaStConv sees them (``remove_self_loops``,
    ``add_self_loops``; repeated edges count as often as they appear): (counts (n,), sources
    (sum counts,) sorted by target)."""
    src, dst = ei[0].cpu().numpy(), ei[1].cpu().numpy()
    keep = src != dst
    src, dst = np.r_[src[keep], np.arange(n)], np.r_[dst[keep], np.arange(n)]
    order = np.argsort(dst, kind="stable")
    return np.bincount(dst, minlength=n), src[order]


def make_groups(counts, sources, rows, device):
    """The groups of ``Plan`` for the output vertices ``rows`` (input-vertex indices, (m,))."""
    start = np.r_[0, np.cumsum(counts)[:-1]]
    K = counts[rows]
    groups = []
    for k in np.unique(K):
        pos = np.nonzero(K == k)[0]
        centre = rows[pos]
        nbr = sources[start[centre][:, None] + np.arange(k)[None, :]]
        groups.append((int(k), torch.as_tensor(centre, device=device), torch.as_tensor(pos, device=device),
                       torch.as_tensor(nbr, device=device)))
    return groups


BMM_SMALL = 400  # torch's CPU bmm multiplies products under this many multiply-adds in a naive loop
TINY = 1e-30  # a steering sum below this (far-apart logits) is recomputed by a plain softmax


def factors(s, c):
    """Per vertex row, A = exp(s - max_h s) and B = exp(c - s - max_h (c - s)), (n b, H) each:
    softmax_h(s_j - s_i + c) = A_j B_i / sum_h A_j B_i, one exp per vertex and head instead of
    one per edge and head (the per-row shifts cancel in the normalisation)."""
    A = (s - s.amax(1, keepdim=True)).exp_()
    t = c - s
    B = (t - t.amax(1, keepdim=True)).exp_()
    return A, B


def _steer(GA, B, s, c, flat, ctr, kb, K, H, out):
    """p (kb, K, H) = softmax_h(s_j - s_i + c) into ``out``, from the gathered A_j (GA, a
    (kb, K, H) view) and the centres' B_i; rows whose sum is below TINY (logits more than about
    60 apart between heads) are recomputed by ``torch.softmax`` of the logits themselves."""
    torch.mul(GA, B.index_select(0, ctr).view(kb, 1, H), out=out)
    S = out.sum(-1, keepdim=True)
    out.div_(S)
    low = S.view(-1) < TINY
    if bool(low.any()):
        r = low.nonzero().view(-1)
        lg = s.index_select(0, flat.view(kb * K)[r]) - s.index_select(0, ctr.repeat_interleave(K)[r]) + c
        out.view(kb * K, H)[r] = torch.softmax(lg, -1)
    return out


def _steer_grad(p, dP, K):
    """dL/dlogits (kb, K, H) from the softmax p and dP = K dL/dp (the 1/K of the mean is
    applied here)."""
    return (p * (dP - (p * dP).sum(-1, keepdim=True))).div_(K)


def _aggregate(p, GA, ci, Ts, w):
    """T (kb, H ci) = [sum_k p_kh x_k]_h / K of a chunk from p (kb, K, H) and the gathered GA
    (kb, K, >= ci), x in its first ci columns; written into worker w's buffer ``Ts[w]``. Where
    K H ci < BMM_SMALL and the extra columns lift the product past it, they are multiplied too:
    torch's naive small-matrix bmm kernel is 2x slower than its batched BLAS path."""
    kb, K, H = p.shape
    if Ts[w] is None or Ts[w].numel() < kb * H * ci:
        Ts[w] = p.new_empty(kb * H * ci)
    T = Ts[w][:kb * H * ci].view(kb, H, ci)
    if K * H * ci < BMM_SMALL <= K * H * GA.shape[2]:
        T.copy_(torch.bmm(p.transpose(1, 2), GA)[..., :ci])
    else:
        torch.bmm(p.transpose(1, 2), GA[..., :ci], out=T)
    return T.div_(K).view(kb, H * ci)


def _sum(ts):
    """The workers' accumulators summed in worker order (deterministic for a given thread count)."""
    out = ts[0]
    for t in ts[1:]:
        out += t
    return out


class AggregateFirst(torch.autograd.Function):
    r"""y_i = b + (1/K_i) [sum_j p_ij1 x_j || ... || sum_j p_ijH x_j] Wt, p_ij = softmax_h(s_j - s_i + c).

    ``forward(x, s, c, Wt, bias, plan)``: x (n_in b, c_in) and s (n_in b, H) vertex-major,
    c (H,), Wt (H c_in, c_out), bias (c_out,) or None; returns (n_out b, c_out). A chunk gathers
    [x_j | A_j] in one ``index_select``. Kept for the backward: the steering weights p (E b H
    floats, 1/c_out of FeaStConv's (E b, H c_out) messages); the backward gathers x again,
    recomputes T chunk by chunk (cheaper than keeping it: a fresh (n b, H c_in) buffer costs
    its page faults, 184 MB in the thesis's largest layer), accumulates dWt^T as dy^T T and
    scatters [dx | ds] in one ``index_add_``; it returns dx, ds, dc, dWt, db."""

    @staticmethod
    def forward(ctx, x, s, c, Wt, bias, plan):
        ci, H, co, b = x.shape[1], s.shape[1], Wt.shape[1], plan.b
        y = x.new_empty(plan.n_out * b, co)
        A, B = factors(s, c)
        XA = torch.cat([x, A], 1)
        P = x.new_empty(plan.p_size)
        Ts = [None] * plan.workers  # per worker: a T buffer reused chunk after chunk (in cache)

        def work(w):
            for g, s0, s1 in plan.work[w]:
                K, kb, flat, ctr, (a, z) = plan.rows(g, s0, s1)
                GA = XA.index_select(0, flat).view(kb, K, ci + H)
                p = _steer(GA[..., ci:], B, s, c, flat, ctr, kb, K, H, plan.p_slice(P, g, s0, s1, H))
                Tk = _aggregate(p, GA, ci, Ts, w)  # (sum_j p_ijh x_j / K)_h
                if bias is None:
                    torch.mm(Tk, Wt, out=y[a:z])
                else:
                    torch.addmm(bias, Tk, Wt, out=y[a:z])

        in_workers(work, plan.workers)
        ctx.save_for_backward(x, P, Wt)
        ctx.plan, ctx.has_bias, ctx.H = plan, bias is not None, H
        return plan.to_vertex_order(y).view(-1, co)

    @staticmethod
    @once_differentiable
    def backward(ctx, gy):
        x, P, Wt = ctx.saved_tensors
        plan, H = ctx.plan, ctx.H
        ci = x.shape[1]
        gy = plan.to_plan_order(gy)
        gb = gy.sum(0) if ctx.has_bias and ctx.needs_input_grad[4] else None
        W = plan.workers
        gxss = [x.new_zeros(x.shape[0], ci + H) for _ in range(W)]  # [dx | ds]
        gcs = [x.new_zeros(H) for _ in range(W)]
        gWs = [Wt.new_zeros(Wt.shape[1], Wt.shape[0]) for _ in range(W)]  # dWt^T
        Ts = [None] * W

        def work(w):
            for g, s0, s1 in plan.work[w]:
                K, kb, flat, ctr, (a, z) = plan.rows(g, s0, s1)
                p = plan.p_slice(P, g, s0, s1, H)
                G = x.index_select(0, flat).view(kb, K, ci)
                # T again (cheaper than keeping it: a fresh (n b, H c_in) buffer costs its page faults)
                gWs[w].addmm_(gy[a:z].t(), _aggregate(p, G, ci, Ts, w))  # dy^T T: 10x faster than T^T dy for c_out = 3
                dT = torch.mm(gy[a:z], Wt.t()).view(kb, H, ci)  # dL/d(K T)
                dP = torch.bmm(G, dT.transpose(1, 2))  # (kb, K, H): <x_j, dT_h>
                # [dx_j | ds_j] scattered in one index_add_ (bmm's out= a strided view is 10x slower)
                d = torch.cat([torch.bmm(p, dT).div_(K), _steer_grad(p, dP, K)], 2)
                dl = d[..., ci:]
                gxss[w].index_add_(0, flat, d.view(kb * K, ci + H))
                gxss[w][:, ci:].index_add_(0, ctr, dl.sum(1), alpha=-1)
                gcs[w] += dl.sum((0, 1))

        in_workers(work, W)
        gxs = _sum(gxss)
        return gxs[:, :ci], gxs[:, ci:], _sum(gcs), _sum(gWs).t(), gb, None


class TransformFirst(torch.autograd.Function):
    r"""y_i = b + (1/K_i) sum_j sum_h p_ijh Z_jh, p_ij = softmax_h(s_j - s_i + c), Z_j = W x_j.

    ``forward(Z, s, c, bias, plan)``: Z (n_in b, H c_out) (head h in columns h c_out ..
    (h + 1) c_out, as ``FeaStConv.lin``), s (n_in b, H), c (H,), bias (c_out,) or None; returns
    (n_out b, c_out). A chunk gathers [Z_jh | A_jh]_h in one ``index_select``; p is kept for the
    backward, which gathers Z again and returns dZ, ds, dc, db."""

    @staticmethod
    def forward(ctx, Z, s, c, bias, plan):
        H, b = s.shape[1], plan.b
        w = Z.shape[1]
        co = w // H
        y = Z.new_empty(plan.n_out * b, co)
        A, B = factors(s, c)
        n_in = Z.shape[0]
        ZA = torch.cat([Z.view(n_in, H, co), A.view(n_in, H, 1)], 2).view(n_in, H * (co + 1))  # [Z_jh | A_jh] per head
        P = Z.new_empty(plan.p_size)

        def work(wk):
            for g, s0, s1 in plan.work[wk]:
                K, kb, flat, ctr, (a, z) = plan.rows(g, s0, s1)
                GA = ZA.index_select(0, flat).view(kb, K * H, co + 1)
                p = _steer(GA[..., co].view(kb, K, H), B, s, c, flat, ctr, kb, K, H, plan.p_slice(P, g, s0, s1, H))
                Yk = torch.bmm(p.view(kb, 1, K * H), GA[..., :co]).view(kb, co).div_(K)
                if bias is not None:
                    Yk += bias
                y[a:z] = Yk

        in_workers(work, plan.workers)
        ctx.save_for_backward(Z, P)
        ctx.plan, ctx.has_bias, ctx.H = plan, bias is not None, H
        return plan.to_vertex_order(y).view(-1, co)

    @staticmethod
    @once_differentiable
    def backward(ctx, gy):
        Z, P = ctx.saved_tensors
        plan, H = ctx.plan, ctx.H
        co = Z.shape[1] // H
        gy = plan.to_plan_order(gy)
        W = plan.workers
        wz = H * co
        gzss = [Z.new_zeros(Z.shape[0], wz + H) for _ in range(W)]  # [dZ | ds]
        gcs = [Z.new_zeros(H) for _ in range(W)]

        def work(w):
            for g, s0, s1 in plan.work[w]:
                K, kb, flat, ctr, (a, z) = plan.rows(g, s0, s1)
                p = plan.p_slice(P, g, s0, s1, H)
                dY = gy[a:z]  # (kb, co)
                G = Z.index_select(0, flat).view(kb, K * H, co)
                dP = torch.bmm(G, dY.view(kb, co, 1)).view(kb, K, H)
                # [dZ_j | ds_j] in one index_add_: dZ_jh = p_ijh dY_i / K, an outer product per row
                dG = (p.reshape(kb, K * H, 1) * dY.view(kb, 1, co)).view(kb, K, wz).div_(K)
                d = torch.cat([dG, _steer_grad(p, dP, K)], 2)
                gzss[w].index_add_(0, flat, d.view(kb * K, wz + H))
                gzss[w][:, wz:].index_add_(0, ctr, d[..., wz:].sum(1), alpha=-1)
                gcs[w] += d[..., wz:].sum((0, 1))

        in_workers(work, W)
        gb = gy.sum(0) if ctx.has_bias and ctx.needs_input_grad[3] else None
        gzs = _sum(gzss)
        return gzs[:, :wz], gzs[:, wz:], _sum(gcs), gb, None


class FeaSt(nn.Module):
    r"""FeaStNet feature-steered graph convolution (torch_geometric FeaStConv's parameters, evaluated in the cheaper order).

    Over the level's edges, N(i) the neighbours of vertex i, with H weight matrices W_h:

        x'_i = b + sum_{j in N(i) u {i}} 1/|N(i) u {i}| sum_{h=1}^{H} q_h(x_i, x_j) W_h x_j,
        q_h(x_i, x_j) = softmax_h(u_h^T (x_j - x_i) + c_h)

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy (any sampler: only the
            level's ``edges`` are read).
        level (int): the level the convolution works on (stride 1).
        heads (int): H, the number of weight matrices (default 8).
        order (str): ``auto`` (default: ``transform`` where H c_out < c_in, else
            ``aggregate``; see the module docstring), ``aggregate``, ``transform``, or ``edges``
            (torch_geometric's ``FeaStConv.forward`` itself: W x_j per edge, the model pooling
            after the conv; slow, the reference).
        init (str): ``feastconv`` (default: the weights ``FeaStConv`` draws, as the thesis
            trained) or ``variance`` (beyond the thesis: W_h scaled by sqrt(3H) after that draw,
            so that a layer passes its input's variance on; see below).

    Initialisation. ``FeaStConv`` draws each W_h with entries ~ U(-1/sqrt(c_in), 1/sqrt(c_in)),
    variance 1/(3 c_in), so W_h x has per-channel variance var(x)/3 for x of independent
    channels; with the steering weights near uniform at the start (q_h ~ 1/H), x'_i averages H
    independent such products: variance var(x)/(3H), about 1/24 of the input's with H = 8. Five
    layers of it take the code's variation to ~1e-3 of itself at the output, which is why a
    FeaStNet decoder stays at the mean shape within the CPU studies' budget
    (``benchmarks/decoder_signal.py``, docs/methods/autoencoders.md). ``init: variance``
    multiplies W_h by sqrt(3H) after FeaStConv's draw, so var(x'_i - b) = var(x) at the start;
    the parameters, the forward and the checkpoints are FeaStConv's as before.

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out) (a view of a vertex-major tensor: use ``reshape``, not
          ``view``); with ``rows`` (m,): (b, m, c_out); ``forward_up``: input (b, n_coarse, c_in)

    Parameters (``state_dict``): ``conv.lin.weight`` (H c_out, c_in) = [W_1; ..; W_H],
    ``conv.u.weight`` (H, c_in) = [u_1; ..; u_H], ``conv.c`` (H,), ``conv.bias`` (c_out,), as
    ``FeaStConv`` names them. ``reset_parameters()`` re-draws FeaStConv's W_h and u_h (its linear
    layers' initialisation) and c, b ~ N(0, 0.1^2); FeaStConv draws them itself when it is
    constructed.
    """

    name = "feast"
    build_args = CONV_BUILD_ARGS
    strided = False
    fuses_pooling = True  # forward(x, rows=...) and forward_up(x, up): pooling fused into the conv
    ORDERS = ("auto", "aggregate", "transform", "edges")
    INITS = ("feastconv", "variance")

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, heads: int = 8,
                 order: str = "auto", init: str = "feastconv"):
        super().__init__()
        # deferred: torch_geometric adds ~1.3 s of import time (measured on top of torch) to every
        # `fwk` command that loads the plugins; only this conv needs it, when it is built
        from torch_geometric.nn import FeaStConv

        if order not in self.ORDERS:
            raise RecipeError(f"conv feast: order must be one of {', '.join(self.ORDERS)}, not {order!r}")
        if init not in self.INITS:
            raise RecipeError(f"conv feast: init must be one of {', '.join(self.INITS)}, not {init!r}")
        lv = hierarchy.levels[level]
        self.n = lv.n_vertices
        self.register_buffer("edges", edge_index(lv.edges, lv.n_vertices, self_loops=False))
        self.conv = FeaStConv(in_channels, out_channels, heads=heads, add_self_loops=True)  # initialises itself
        if order == "auto":
            order = "transform" if heads * out_channels < in_channels else "aggregate"
        self.order = order
        if order == "edges":
            self.fuses_pooling = False  # the model pools after the conv, as it did with FeaStConv alone
        self.heads = heads
        self.init = init
        self._scale_weights()
        self._nbh = neighbourhoods(self.edges, self.n)  # (counts, sources) as numpy arrays
        self._plans = {}  # (rows key, b, device, threads) -> Plan

    def reset_parameters(self) -> None:
        """Re-draw FeaStConv's parameters (its own ``reset_parameters``), then ``init``'s scaling."""
        self.conv.reset_parameters()
        self._scale_weights()

    def _scale_weights(self) -> None:
        if self.init == "variance":
            with torch.no_grad():
                self.conv.lin.weight.mul_(float(np.sqrt(3 * self.heads)))

    def _plan(self, rows, b, device, width):
        threads = torch.get_num_threads() if device.type == "cpu" else 1
        key = (None if rows is None else id(rows), b, str(device), threads)
        hit = self._plans.get(key)
        if hit is not None and (rows is None or hit[0] is rows):
            return hit[1]
        r = np.arange(self.n) if rows is None else rows.cpu().numpy()
        plan = Plan(make_groups(*self._nbh, r, device), len(r), b, width, threads, self.heads)
        if len(self._plans) > 8:
            self._plans.clear()
        self._plans[key] = (rows, plan)
        return plan

    def forward(self, x, rows=None):
        """x (b, n, c_in) -> (b, n, c_out); with ``rows`` (m,) int64 only those output vertices,
        (b, m, c_out) = forward(x)[:, rows] (a pooling that keeps a vertex subset, fused)."""
        if self.order == "edges":
            y = self._edges(x)
            return y if rows is None else y[:, rows]
        b, n, c = x.shape
        xv = x.transpose(0, 1).reshape(n * b, c)  # vertex-major rows (vertex, sample)
        if self.order == "aggregate":
            return self._aggregate(xv, b, rows)
        conv = self.conv
        with torch.autocast(x.device.type, enabled=False):
            xv = xv.to(conv.lin.weight.dtype)
            return self._transform(xv @ conv.lin.weight.t(), xv @ conv.u.weight.t(), b, rows)

    def forward_up(self, x, up):
        """forward(U x) for an up-sampling U (``up``, a sparse (n, n_coarse) COO tensor, e.g.
        ``Hierarchy.up`` through ``fwk.graph.torch_sparse``): x (b, n_coarse, c_in) -> (b, n, c_out).
        In the ``transform`` order W x and U_s x (the steering products) are taken on the coarse
        vertices and up-sampled (U (x W^T) = (U x) W^T); otherwise U x is formed first."""
        if self.order != "transform":
            return self(sparse_apply(up, x))
        conv = self.conv
        with torch.autocast(x.device.type, enabled=False):
            x = x.to(conv.lin.weight.dtype)
            zs = sparse_apply(up, torch.cat([x @ conv.lin.weight.t(), x @ conv.u.weight.t()], -1))  # (b, n, H c_out + H)
            b, n, w = zs.shape
            zs = zs.transpose(0, 1).reshape(n * b, w)
            H = self.heads
            return self._transform(zs[:, :w - H], zs[:, w - H:], b, None)

    def _aggregate(self, xv, b, rows):
        conv = self.conv
        H, co = self.heads, conv.out_channels
        with torch.autocast(xv.device.type, enabled=False):
            xv = xv.to(conv.lin.weight.dtype).contiguous()
            ci = xv.shape[1]
            s = xv @ conv.u.weight.t()
            Wt = conv.lin.weight.view(H, co, ci).transpose(1, 2).reshape(H * ci, co)
            plan = self._plan(rows, b, xv.device, ci + H)
            y = AggregateFirst.apply(xv, s, conv.c, Wt, conv.bias, plan)
        return y.view(plan.n_out, b, co).transpose(0, 1)

    def _transform(self, Z, s, b, rows):
        conv = self.conv
        co = conv.out_channels
        plan = self._plan(rows, b, Z.device, Z.shape[1] + s.shape[1])
        y = TransformFirst.apply(Z.contiguous(), s.contiguous(), conv.c, conv.bias, plan)
        return y.view(plan.n_out, b, co).transpose(0, 1)

    def _edges(self, x):
        """torch_geometric's FeaStConv on the batch as one graph of b n nodes (the reference path)."""
        b, n, c = x.shape
        off = (torch.arange(b, device=x.device) * n).repeat_interleave(self.edges.shape[1])
        ei = self.edges.repeat(1, b) + off
        return self.conv(x.reshape(b * n, c), ei).reshape(b, n, -1)


@hookimpl
def fwk_register_convs():
    return [FeaSt]
