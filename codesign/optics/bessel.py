"""Differentiable Bessel functions of the first kind J_0..J_N for real x >= 0.

Why hand-written: torch ships only J0 and J1 (``torch.special.bessel_j0/j1``), without any integer order n > 1,
and its float64 J0/J1 are only accurate to ~4e-7 for 5 < x < 25 (measured against scipy). The half-ring phase
needs J_0 and the odd orders up to 35 (or more) at arguments up to ~2*pi*r_max ~ 600, with the gradient in x.

Algorithm (all orders 0..N at once, computed in float64 whatever the input dtype):
  * x < 1: the power series sum_k (-x^2/4)^k / (k! (n+k)!) * (x/2)^n; no cancellation there and it
    underflows gracefully to 0 for tiny x and large n (x = 1e-12, n = 60 gives 0, not NaN).
  * 1 <= x < X_MILLER: Miller's backward recurrence J_{k-1} = (2k/x) J_k - J_{k+1} from an order K well above
    max(N, x), normalized with J_0 + 2 sum_k J_{2k} = 1. Backward recurrence is stable for every order.
  * x >= X_MILLER (>= N + 2): J_0, J_1 from Hankel's asymptotic expansion (accurate to ~1e-16 for x >= 25),
    then forward recurrence J_{n+1} = (2n/x) J_n - J_{n-1}, which is stable while n < x.
The gradient uses dJ_0/dx = -J_1 and dJ_n/dx = (J_{n-1} - J_{n+1}) / 2 (one extra order is computed for it).
"""
from __future__ import annotations

import math

import torch

_X_SERIES = 1.0  # below this the power series is exact to rounding
_X_ASYMPTOTIC_MIN = 25.0  # Hankel's expansion reaches ~1e-16 from here on (smallest term ~ exp(-2x))


def _miller_limit(n_max: int) -> float:
    # Forward recurrence needs n < x for every requested order, so Miller must cover x up to n_max + 2.
    return max(_X_ASYMPTOTIC_MIN, float(n_max + 2))


def _series(x: torch.Tensor, n_max: int, out: torch.Tensor, rows: dict[int, int]) -> None:
    """Power series, valid (to rounding) for 0 <= x < 1: J_n into ``out[rows[n]]`` for every n in ``rows``."""
    wanted = sorted(rows)
    orders = torch.tensor(wanted, dtype=x.dtype, device=x.device)[:, None]
    half = (x / 2)[None, :]
    lead = torch.pow(half, orders) / torch.exp(torch.lgamma(orders + 1))  # (x/2)^n / n!, pow(0, 0) = 1
    q = -(half**2)
    term = torch.ones_like(lead)
    total = torch.ones_like(lead)
    for k in range(1, 14):  # (1/4)^13 / 13! ~ 1e-18: converged for x < 1
        term = term * q / (k * (orders + k))
        total = total + term
    out[[rows[n] for n in wanted]] = lead * total


def _miller(x: torch.Tensor, n_max: int, out: torch.Tensor, rows: dict[int, int]) -> None:
    """Miller's normalized backward recurrence, for 1 <= x <= _miller_limit(n_max): J_n into ``out[rows[n]]``.
    In place: two buffers swap roles, so the ~90 steps allocate nothing."""
    x_hi = _miller_limit(n_max)
    # Start order: above both n_max and x, plus a margin that grows like x^(1/3) (width of the turning region).
    start = int(math.ceil(max(n_max, x_hi) + 30 + 6 * x_hi ** (1 / 3)))
    start += start % 2  # even, so the normalization sum sees every even order
    j_next = torch.zeros_like(x)
    j_cur = torch.full_like(x, 1e-280)
    norm = torch.zeros_like(x)
    inv_x = 1.0 / x
    stored: list[int] = []
    tmp = torch.empty_like(x)
    for k in range(start, 0, -1):
        # J_{k-1} = (2k / x) J_k - J_{k+1} into J_{k+1}'s buffer, rounded as ((2k) inv_x) J_k - J_{k+1} (the
        # library's values stay the same to the last bit)
        torch.mul(inv_x, 2 * k, out=tmp).mul_(j_cur)
        torch.sub(tmp, j_next, out=j_next)
        j_next, j_cur = j_cur, j_next
        order = k - 1
        if order % 2 == 0 and order > 0:
            norm.add_(j_cur, alpha=2)
        if order in rows:
            out[rows[order]].copy_(j_cur)
            stored.append(rows[order])
        # Keep magnitudes in range: for x >= 1 and start <= ~200 growth is below 1e250, but rescale anyway
        # whenever values get large so that no configuration can overflow.
        if k % 16 == 0:
            big = torch.abs(j_cur) > 1e200
            if bool(big.any()):
                scale = torch.where(big, 1e-200, 1.0)
                j_cur.mul_(scale), j_next.mul_(scale), norm.mul_(scale)
                for i in stored:
                    out[i].mul_(scale)
    norm.add_(j_cur)  # + J_0
    for i in rows.values():
        out[i].div_(norm)


def _hankel_j0_j1(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """J_0 and J_1 from Hankel's asymptotic expansion, for x >= 25 (float64)."""
    res = []
    for nu in (0, 1):
        mu = 4.0 * nu * nu
        p = torch.ones_like(x)
        q = torch.zeros_like(x)
        term = torch.ones_like(x)
        inv8x = 1.0 / (8.0 * x)
        for k in range(1, 40):
            term = term * (mu - (2 * k - 1) ** 2) / k * inv8x
            if k % 2 == 1:
                q = q + (term if (k // 2) % 2 == 0 else -term)
            else:
                p = p + (-term if (k // 2) % 2 == 1 else term)
        chi = x - (nu / 2 + 0.25) * math.pi
        res.append(torch.sqrt(2.0 / (math.pi * x)) * (p * torch.cos(chi) - q * torch.sin(chi)))
    return res[0], res[1]


def _forward(x: torch.Tensor, n_max: int, out: torch.Tensor, rows: dict[int, int]) -> None:
    """Hankel J_0, J_1 then forward recurrence, valid for x >= _miller_limit(n_max): J_n into ``out[rows[n]]``."""
    prev, cur = _hankel_j0_j1(x)
    inv_x = 1.0 / x
    for n, j in ((0, prev), (1, cur)):
        if n in rows:
            out[rows[n]].copy_(j)
    tmp = torch.empty_like(x)
    for n in range(1, n_max):
        torch.mul(inv_x, 2 * n, out=tmp).mul_(cur)
        torch.sub(tmp, prev, out=prev)  # J_{n+1} = (2n / x) J_n - J_{n-1}, in J_{n-1}'s buffer
        prev, cur = cur, prev
        if n + 1 in rows:
            out[rows[n + 1]].copy_(cur)


_RUN_IN_PLACE = 32768  # runs at least this long are evaluated in place, one recurrence each
_MAX_RUNS = 64  # above this many contiguous runs of one regime, gather and scatter instead (unordered x)


def _regime_labels(xd: torch.Tensor, x_hi: float) -> torch.Tensor:
    """Each x's regime: 0 series (x < 1), 1 Miller (1 <= x < x_hi), 2 Hankel + forward recurrence."""
    return (xd >= _X_SERIES).to(torch.int8) + (xd >= x_hi).to(torch.int8)


def _regime_runs(label: torch.Tensor) -> list[list[tuple[int, int]]] | None:
    """For each regime (series, Miller, forward) the contiguous runs [a, b) of the flattened x that fall in it,
    or None when x is too unordered for runs to pay. Ordered inputs (the half-ring's distinct radii times each
    ring's radius: one ascending row per ring) split into a few runs, each evaluated in place on a view of the
    table: no gather of x, no scatter of a part into the table, and each run's recurrence works in cache."""
    edges = torch.nonzero(label[1:] != label[:-1]).squeeze(-1) + 1
    if edges.numel() >= _MAX_RUNS:
        return None
    bounds = [0] + edges.tolist() + [label.numel()]
    kinds = label[torch.tensor(bounds[:-1], device=label.device)].tolist()
    runs: list[list[tuple[int, int]]] = [[], [], []]
    for kind, a, b in zip(kinds, bounds[:-1], bounds[1:]):
        runs[kind].append((a, b))
    return runs


def bessel_rows(x: torch.Tensor, orders, out: torch.Tensor | None = None) -> torch.Tensor:
    """J_n(x) for each n of ``orders`` (distinct, >= 0), without autograd, in float64: shape (len(orders),
    x.numel()), row i is J_{orders[i]} at the flattened x (rows contiguous: the recurrences write whole rows).
    ``out``: a contiguous float64 tensor of that many elements to write into (a reused workspace)."""
    orders = [int(n) for n in orders]
    n_max = max(max(orders), 1)
    rows = {n: i for i, n in enumerate(orders)}
    xd = x.detach().to(torch.float64).reshape(-1)
    if out is None:
        out = torch.empty(len(orders), xd.numel(), dtype=torch.float64, device=xd.device)
    else:
        out = out.view(len(orders), xd.numel())
    if xd.numel() == 0:
        return out
    fns = (_series, _miller, _forward)
    label = _regime_labels(xd, _miller_limit(n_max))
    runs = _regime_runs(label)
    if runs is not None:
        for fn, spans in zip(fns, runs):
            in_place = spans if len(spans) == 1 else [(a, b) for a, b in spans if b - a >= _RUN_IN_PLACE]
            short = [(a, b) for a, b in spans if (a, b) not in in_place]
            for a, b in in_place:
                fn(xd[a:b], n_max, out[:, a:b], rows)
            if short:  # one recurrence over all short runs (~100 steps of Python overhead whatever the length),
                # then slice copies back: still no index_put
                part = torch.empty(len(orders), sum(b - a for a, b in short), dtype=torch.float64, device=xd.device)
                fn(torch.cat([xd[a:b] for a, b in short]), n_max, part, rows)
                at = 0
                for a, b in short:
                    out[:, a:b].copy_(part[:, at:at + b - a])
                    at += b - a
        return out
    for kind, fn in enumerate(fns):
        idx = torch.nonzero(label == kind).squeeze(-1)
        if idx.numel() == 0:
            continue
        part = torch.empty(len(orders), idx.numel(), dtype=torch.float64, device=xd.device)
        fn(xd[idx], n_max, part, rows)
        out[:, idx] = part
    return out


def bessel_j_table(x: torch.Tensor, n_max: int) -> torch.Tensor:
    """J_0(x) .. J_{n_max}(x) without autograd, computed in float64.

    Args:
        x: real tensor, any shape, values >= 0 (dimensionless argument).
        n_max: highest order, >= 1.
    Returns:
        float64 tensor of shape (*x.shape, n_max + 1) (a view of the order-major table).
    """
    return bessel_rows(x, range(n_max + 1)).T.reshape(*x.shape, n_max + 1)


class _BesselOrders(torch.autograd.Function):
    """J_n(x) for the orders asked, order-major (K, *x.shape); saved for the gradient: the rows n +- 1 only."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, orders: tuple[int, ...]) -> torch.Tensor:
        need = sorted({1 if n == 0 else m for n in orders for m in ((n - 1, n + 1) if n else (1,))} | set(orders))
        table = bessel_rows(x, need)
        at = {n: i for i, n in enumerate(need)}
        ctx.save_for_backward(table)
        ctx.at, ctx.orders, ctx.shape = at, orders, x.shape
        return table[[at[n] for n in orders]].to(x.dtype).reshape(len(orders), *x.shape)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        """grad_x = sum_n g_n J_n', J_0' = -J_1, J_n' = (J_{n-1} - J_{n+1}) / 2: one pass over the saved rows."""
        (table,) = ctx.saved_tensors
        g = grad_out.reshape(len(ctx.orders), -1).to(torch.float64)
        grad_x = torch.zeros(table.shape[1], dtype=torch.float64, device=table.device)
        for i, n in enumerate(ctx.orders):
            if n == 0:
                grad_x.addcmul_(g[i], table[ctx.at[1]], value=-1.0)
            else:
                grad_x.addcmul_(g[i], table[ctx.at[n - 1]] - table[ctx.at[n + 1]], value=0.5)
        return grad_x.reshape(ctx.shape).to(grad_out.dtype), None


class _Workspace:
    """Reusable float64 tables for bessel_mix, keyed by shape and device. A table is handed out again only when
    nothing else holds it (an autograd graph that saved it keeps it until its backward or its release), so reuse
    can never overwrite values a pending backward needs. Why: at the paper's sampling the table is ~100 MB, and a
    fresh allocation of that size is mapped afresh by the OS on every call; its page faults cost about as much as
    the Bessel recurrences themselves (docs/optics.md). At most ``keep`` tables are held (the most recently
    used: a search at one sampling and its check on a finer grid)."""

    def __init__(self, keep: int = 2):
        self.keep = keep
        self.tables: dict[tuple, torch.Tensor] = {}

    def take(self, shape: tuple, device: torch.device) -> torch.Tensor:
        key = (tuple(shape), str(device))
        t = self.tables.pop(key, None)
        if t is None or t._use_count() > 1:  # in use by a graph: leave it to that graph, make a new one
            t = torch.empty(shape, dtype=torch.float64, device=device)
        self.tables[key] = t  # most recently used last
        while len(self.tables) > self.keep:
            self.tables.pop(next(iter(self.tables)))
        return t


_WORKSPACE = _Workspace()


class _BesselMix(torch.autograd.Function):
    """out[k] = sum_r w[r, k] J_{orders[k]}(x[r]) from one float64 table of the orders and their neighbours."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w: torch.Tensor, orders: tuple[int, ...]) -> torch.Tensor:
        groups: dict[int, list[int] | slice] = {}
        for k, n in enumerate(orders):
            groups.setdefault(n, []).append(k)
        for n, ks in groups.items():  # outputs of one order side by side: a view, not a gather
            if ks == list(range(ks[0], ks[-1] + 1)):
                groups[n] = slice(ks[0], ks[-1] + 1)
        need = sorted(set(orders) | {m for n in groups for m in ((n - 1, n + 1) if n else (1,))})
        at = {n: i for i, n in enumerate(need)}
        table = _WORKSPACE.take((len(need), *x.shape), x.device)
        bessel_rows(x, need, out=table)  # (T, R, U)
        w64 = w.detach().to(torch.float64)
        out = torch.empty(len(orders), x.shape[1], dtype=torch.float64, device=x.device)
        for n, ks in groups.items():  # one (k_n, R) @ (R, U) product per distinct order: no copy of the table
            out[ks] = w64[:, ks].T @ table[at[n]]
        ctx.save_for_backward(table, w64)
        ctx.groups, ctx.at, ctx.dtypes = groups, at, (x.dtype, w.dtype)
        return out.to(x.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        """grad_w[r, k] = sum_u g[k] J_n(x[r]); grad_x[r] = sum_n (w[:, k_n] @ g[k_n])[r] J_n'(x[r]), J_0' = -J_1,
        J_n' = (J_{n-1} - J_{n+1}) / 2."""
        table, w64 = ctx.saved_tensors
        at = ctx.at
        g = grad_out.to(torch.float64)
        grad_x = grad_w = None
        if ctx.needs_input_grad[1]:
            grad_w = torch.empty_like(w64)
            for n, ks in ctx.groups.items():
                grad_w[:, ks] = table[at[n]] @ g[ks].T
            grad_w = grad_w.to(ctx.dtypes[1])
        if ctx.needs_input_grad[0]:
            grad_x = torch.zeros(table.shape[1:], dtype=torch.float64, device=table.device)
            mixed, slope = torch.empty_like(grad_x), torch.empty_like(grad_x)
            for n, ks in ctx.groups.items():
                torch.matmul(w64[:, ks], g[ks], out=mixed)
                if n == 0:
                    grad_x.addcmul_(mixed, table[at[1]], value=-1.0)
                else:
                    torch.sub(table[at[n - 1]], table[at[n + 1]], out=slope)
                    grad_x.addcmul_(mixed, slope, value=0.5)
            grad_x = grad_x.to(ctx.dtypes[0])
        return grad_x, grad_w, None


def bessel_mix(x: torch.Tensor, weights: torch.Tensor, orders) -> torch.Tensor:
    """Differentiable weighted sums of Bessel functions over the rows of x:
    ``out[k, u] = sum_r weights[r, k] J_{orders[k]}(x[r, u])``, shape (len(orders), U), in x's dtype.

    What a radial synthesis such as the half-ring's needs (Q0 and the A_m / B_m profiles: a few rings r, many
    radii u): the sums are taken in float64 straight from one table of the distinct orders (and the neighbours
    their derivatives need), so no (K, R, U) tensor of Bessel values is copied, cast or multiplied; the backward
    reads the same table. Orders may repeat (several outputs of one order; fastest side by side), each in
    [0, 200]. x: (R, U), values >= 0; weights: (R, K). Gradients to x and weights. Fastest when each row of x
    is ordered (see bessel_rows)."""
    orders = tuple(int(n) for n in orders)
    if not orders or min(orders) < 0 or max(orders) > 200:
        raise ValueError(f"bessel_mix: orders must be integers in [0, 200], got {orders!r}")
    if x.dim() != 2 or weights.dim() != 2 or weights.shape != (x.shape[0], len(orders)):
        raise ValueError(f"bessel_mix: x must be (R, U) and weights (R, {len(orders)}) (one column per order); got "
                         f"x {tuple(x.shape)}, weights {tuple(weights.shape)}")
    _check_x(x)
    return _BesselMix.apply(x, weights, orders)


def _check_x(x: torch.Tensor) -> None:
    if not torch.is_floating_point(x):
        raise ValueError(f"bessel_j: x must be a real floating tensor (float32/float64), got {x.dtype}")
    if x.numel() and not bool((x >= 0).all()):
        raise ValueError("bessel_j: x must be >= 0 and not NaN (got a negative or NaN value)")


def bessel_j(x: torch.Tensor, n_max: int) -> torch.Tensor:
    """Differentiable J_0(x) .. J_{n_max}(x) for real x >= 0.

    Accurate to ~1e-13 absolute in float64 for orders up to >= 60 and x up to >= 1000 (see module docstring);
    float32 inputs are evaluated in float64 and rounded, so they are exact to float32 rounding.

    Args:
        x: real tensor (float32 or float64), any shape, all values >= 0 (dimensionless).
        n_max: highest order wanted, 1 <= n_max <= 200.
    Returns:
        tensor of x's dtype and shape (*x.shape, n_max + 1); entry [..., n] is J_n(x).
    Raises:
        ValueError: if x is not a real floating tensor, holds a negative/NaN value, or n_max is out of range.
    """
    _check_x(x)
    if isinstance(n_max, bool) or not isinstance(n_max, int) or not 1 <= n_max <= 200:
        raise ValueError(f"bessel_j: n_max must be an integer in [1, 200], got {n_max!r}")
    return _BesselOrders.apply(x, tuple(range(n_max + 1))).movedim(0, -1)
