"""Recordings of a position-processing module: X, Y and SUM instead of four channels.

Analogue PSD front ends (Hamamatsu C10443-type, Thorlabs PDP90A-type,
On-Trak-type) output the spot position ``X, Y`` (volts proportional to mm)
and the total photocurrent ``SUM``.  With LEDs switched in turn (time
multiplexing), DC or blinking, the record is a sequence of plateaus, one per
LED slot, separated by dark samples (SUM near zero) or by nothing at all
(the first sample of a slot then blends two LEDs).

:func:`segment_module` splits such a record from the signals alone:

1. *dark* samples: SUM below a threshold found by Otsu's split of
   ``log SUM`` (only when the lower class is at least 10x darker than the
   upper one; otherwise every sample is lit);
2. *emitters*: the dense places of the lit samples in ``(X, Y, log SUM)``
   (a grid of 1 % of the position range by 5 % of SUM; cells holding at
   least 1 % of the lit samples, adjacent cells joined): a plateau sample of
   one LED falls in the same few cells again and again, a transition sample
   lies on the line between two LEDs, in a sparse cell;
3. *mixtures*: a dense place that is a mixture of two denser ones (or of
   one and darkness) is a repeated transition, not an LED (see
   :func:`_drop_blends`);
4. *assignment*: a lit sample belongs to an emitter when it lies within
   ``k_sigma`` robust standard deviations (1.4826 MAD) of the emitter's
   median in X and Y and ``k_sigma_sum`` in log SUM; any other lit sample
   is a transition and is dropped.

Emitters are named ``1, 2, ...`` in the order of their first clean sample,
so a label never depends on the geometry.  Nothing is merged silently: with
``n_emitters`` given, another count raises :class:`InputError`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psdcal.errors import InputError

#: Roles a column of a module recording can have (``-`` skips a column).
ROLES = ("t", "x", "y", "sum", "-")
#: Largest module recording read at once (rows): about 0.5 GB of float64.
MAX_ROWS = 16_000_000

DARK = -1
TRANSITION = -2


def parse_roles(spec: str) -> tuple[str, ...]:
    """``"t,x,y,sum"`` -> ``("t", "x", "y", "sum")``: the role of each column in file order.

    Raises
    ------
    InputError
        An unknown role, a role given twice, or x, y or sum missing.
    """
    roles = tuple(r.strip().lower() for r in str(spec).split(","))
    for r in roles:
        if r not in ROLES:
            raise InputError(f"unknown column role {r!r} in --channels (use t, x, y, sum or - per column)",
                             field="channels")
    named = [r for r in roles if r != "-"]
    if len(set(named)) != len(named):
        raise InputError(f"a column role is given twice in --channels {spec!r}", field="channels")
    for r in ("x", "y", "sum"):
        if r not in roles:
            raise InputError(f"--channels {spec!r} has no '{r}' column", field="channels")
    return roles


def is_module_spec(spec) -> bool:
    """True when a ``--channels`` value names module roles (x, y and sum) rather than four channels."""
    if spec is None:
        return False
    names = [r.strip().lower() for r in str(spec).split(",")]
    return "x" in names and "y" in names and "sum" in names


@dataclass(frozen=True)
class ModuleRecording:
    """X, Y, SUM samples of a position-processing module.

    Attributes
    ----------
    path : str
    t_s : (n,) ndarray
        Sample times, s.
    x, y : (n,) ndarray
        Position outputs, module units (volts).
    sum : (n,) ndarray
        SUM output, module units (volts).
    rate_hz : float
    """

    path: str
    t_s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    sum: np.ndarray
    rate_hz: float


def read_module(path, roles, rate_hz: float | None = None) -> ModuleRecording:
    """Read a module recording: text with one sample per line (comma, space or tab separated).

    A first line that is not numeric is a header and skipped.  ``.npy``
    files (n, n_roles) are read too.

    Parameters
    ----------
    path : str or Path
    roles : sequence of str or str
        Role of each column in file order (:func:`parse_roles`).
    rate_hz : float, optional
        Needed when there is no ``t`` column; with one, it is checked against
        the median time step.

    Raises
    ------
    InputError
        Naming the file, the line and the field.
    """
    path = Path(path)
    roles = parse_roles(",".join(roles) if not isinstance(roles, str) else roles)
    if not path.is_file():
        raise InputError("recording not found", path=path)
    if path.suffix.lower() == ".npy":
        try:
            a = np.load(path, mmap_mode="r", allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - any unreadable NPY is bad input
            raise InputError(f"not a readable .npy file ({type(exc).__name__})", path=path) from None
        if a.ndim != 2 or a.shape[1] != len(roles) or a.dtype.kind not in "iuf":
            raise InputError(f"expected a real (n, {len(roles)}) array for --channels {','.join(roles)}, "
                             f"got {a.dtype} {a.shape}", path=path)
        if a.shape[0] > MAX_ROWS:
            raise InputError(f"{a.shape[0]} rows is more than {MAX_ROWS} (split the recording)", path=path)
        data = np.asarray(a, dtype=float)
        first_line = None
    else:
        data, first_line = _read_text(path, len(roles))
    for j, r in enumerate(roles):
        if r == "-":
            continue
        bad = np.flatnonzero(~np.isfinite(data[:, j]))
        if bad.size:
            line = None if first_line is None else first_line + int(bad[0])
            raise InputError("not a finite number", path=path, line=line, field=r)
    n = data.shape[0]
    if n < 2:
        raise InputError(f"a module recording needs at least 2 samples, got {n}", path=path)
    col = {r: data[:, j] for j, r in enumerate(roles) if r != "-"}
    if "t" in col:
        t = col["t"]
        dt = np.diff(t)
        if np.any(dt <= 0):
            i = int(np.flatnonzero(dt <= 0)[0]) + 1
            raise InputError("time does not increase", path=path,
                             line=None if first_line is None else first_line + i, field="t")
        rate_t = 1.0 / float(np.median(dt))
        if rate_hz is not None and abs(rate_hz - rate_t) > 0.01 * rate_t:
            raise InputError(f"--rate-hz {rate_hz:g} disagrees with the time column ({rate_t:.6g} Hz)",
                             path=path, field="rate_hz")
        rate = rate_t
    else:
        if rate_hz is None or not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise InputError("no 't' column: give a positive --rate-hz", path=path, field="rate_hz")
        rate = float(rate_hz)
        t = np.arange(n) / rate
    return ModuleRecording(str(path), t, col["x"], col["y"], col["sum"], rate)


def _read_text(path: Path, ncol: int):
    rows = []
    first_line = None
    try:
        fh = open(path, encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror})", path=path) from None
    with fh:
        try:
            for lineno, line in enumerate(fh, start=1):
                s = line.strip()
                if not s:
                    continue
                parts = [p for p in s.replace(",", " ").replace("\t", " ").split(" ") if p]
                try:
                    vals = [float(p) for p in parts]
                except ValueError:
                    if first_line is None and not rows:
                        continue  # a header
                    bad = next(p for p in parts if not _is_float(p))
                    raise InputError(f"not a number: {bad!r}", path=path, line=lineno) from None
                if len(vals) != ncol:
                    raise InputError(f"expected {ncol} fields (--channels), found {len(vals)}", path=path,
                                     line=lineno)
                if first_line is None:
                    first_line = lineno
                rows.append(vals)
                if len(rows) > MAX_ROWS:
                    raise InputError(f"more than {MAX_ROWS} rows (split the recording)", path=path)
        except UnicodeDecodeError:
            raise InputError("not a UTF-8 text file", path=path) from None
    if not rows:
        raise InputError("no samples", path=path)
    return np.array(rows, dtype=float), first_line


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class ModuleEmitter:
    """One LED found in a module recording.

    Attributes
    ----------
    emitter : str
    x, y : float
        Median position of its samples, module units.
    sum : float
        Median SUM.
    scatter_x, scatter_y : float
        Standard deviation of its samples (one sample's scatter), module units.
    n_samples : int
        Samples assigned to it.
    first_index : int
        Index of its first sample.
    """

    emitter: str
    x: float
    y: float
    sum: float
    scatter_x: float
    scatter_y: float
    n_samples: int
    first_index: int


@dataclass(frozen=True)
class ModuleSegmentation:
    """The split of a module recording.

    Attributes
    ----------
    labels : (n,) int ndarray
        Emitter index (0-based, in the order of :attr:`emitters`) of each
        sample, :data:`DARK` (-1) or :data:`TRANSITION` (-2).
    emitters : tuple of ModuleEmitter
    dark_threshold : float
        SUM below which a sample is dark (0 when the record has no dark samples).
    n_dark, n_transition : int
    """

    labels: np.ndarray
    emitters: tuple
    dark_threshold: float
    n_dark: int
    n_transition: int


def _otsu_split(v: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of ``v`` (maximises the between-class variance)."""
    hist, edges = np.histogram(v, bins=bins)
    c = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * c)
    mt = m0[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mt * w0 / w0[-1] - m0) ** 2 / (w0 * w1)
    between[~np.isfinite(between)] = -1
    return float(edges[int(np.argmax(between)) + 1])


def dark_threshold(s: np.ndarray) -> float:
    """SUM level separating dark from lit samples (0 when the record has no dark samples)."""
    pos = s[s > 0]
    if pos.size < 4:
        return 0.0
    ls = np.log(pos)
    if ls.max() - ls.min() < 1e-9:
        return 0.0
    cut = _otsu_split(ls)
    lo, hi = ls[ls < cut], ls[ls >= cut]
    if lo.size == 0 or hi.size == 0 or np.median(hi) - np.median(lo) < math.log(10.0):
        return 0.0  # two lit levels (LEDs of different brightness), not dark and lit
    return float(math.exp(0.5 * (np.median(lo) + np.median(hi))))


def _drop_blends(cand, *, rel_tol: float = 0.02):
    """Remove dense places that are mixtures of two stronger emitters.

    When the switching is not synchronous with the sampling, the samples that
    straddle a switch repeat the same mixtures and can form dense places of
    their own.  A module averages X and SUM over the sample time, so a
    mixture of emitters A and B (fraction ``t`` of B) lies at
    ``(1 - t) P_A + t P_B`` with ``SUM = (1 - t) S_A + t S_B``.  A place is
    dropped when it matches such a mixture (position within ``rel_tol`` of
    ``|P_B - P_A|`` off the segment, SUM within ``rel_tol`` of the mixture's,
    ``0.02 < t < 0.98``) and holds fewer than half the samples of the weaker
    of A and B (a real LED on the line between two others, as on a template
    row, has as many samples as they do).
    """
    order = sorted(range(len(cand)), key=lambda j: -cand[j][6])  # stable: the dark end first among equals
    kept: list[int] = []
    for j in order:
        cx, cy, cl, *_, nj = cand[j]
        blend = False
        for ia, a in enumerate(kept):
            for b in kept[ia + 1:]:
                pa = np.array(cand[a][:2])
                pb = np.array(cand[b][:2])
                sa, sb = math.exp(cand[a][2]), math.exp(cand[b][2])
                ab = pb - pa
                L = float(np.hypot(*ab))
                if L == 0 or nj * 2 > min(cand[a][6], cand[b][6]):
                    continue
                t = float(np.dot(np.array([cx, cy]) - pa, ab) / (L * L))
                perp = float(np.hypot(*(np.array([cx, cy]) - pa - t * ab)))
                s_mix = (1 - t) * sa + t * sb
                if 0.02 < t < 0.98 and perp < rel_tol * L and abs(math.exp(cl) - s_mix) < rel_tol * max(sa, sb):
                    blend = True
                    break
            if blend:
                break
        if not blend:
            kept.append(j)
    return [cand[j] for j in sorted(kept)]


def segment_module(x, y, s, *, n_emitters: int | None = None, k_sigma: float = 5.0, k_sigma_sum: float = 3.0,
                   grid_frac: float = 0.01,
                   sum_step: float = 0.05, min_frac: float = 0.01) -> ModuleSegmentation:
    """Split X, Y, SUM samples into emitters, dark samples and transitions (see the module docstring).

    Parameters
    ----------
    x, y, s : (n,) ndarray
        Position outputs and SUM.
    n_emitters : int, optional
        Expected number of LEDs: another count raises :class:`InputError`.
    k_sigma, k_sigma_sum : float
        Assignment tolerance in position and in log SUM, in robust standard
        deviations (SUM is tighter: a sample where an LED switches on or off
        keeps its position, since the module normalises, but not its SUM).
    grid_frac : float
        Grid cell, as a fraction of the lit samples' position range.
    sum_step : float
        Grid cell in ``log SUM``.
    min_frac : float
        A dense cell holds at least this fraction of the lit samples (and 3).

    Returns
    -------
    ModuleSegmentation
    """
    x, y, s = (np.asarray(v, dtype=float) for v in (x, y, s))
    n = x.size
    thr = dark_threshold(s)
    lit = s > thr if thr > 0 else s > 0
    labels = np.full(n, DARK, dtype=int)
    idx = np.flatnonzero(lit)
    if idx.size == 0:
        raise InputError("no lit sample in the recording (SUM never above the dark level)", field="sum")
    xl, yl, ll = x[idx], y[idx], np.log(s[idx])
    span = max(np.percentile(xl, 99) - np.percentile(xl, 1), np.percentile(yl, 99) - np.percentile(yl, 1))
    h = max(grid_frac * span, 1e-12 * max(1.0, float(np.max(np.abs(np.r_[xl, yl])))))
    key = np.stack([np.floor(xl / h), np.floor(yl / h), np.floor(ll / sum_step)], axis=1).astype(np.int64)
    cells, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    heavy = np.flatnonzero(counts >= max(3, min_frac * idx.size))
    # join adjacent heavy cells (26-neighbourhood): union-find over a dict
    where = {tuple(cells[c]): c for c in heavy}
    parent = {c: c for c in heavy}

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    offs = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)]
    for c in heavy:
        ci = cells[c]
        for o in offs:
            d = where.get((ci[0] + o[0], ci[1] + o[1], ci[2] + o[2]))
            if d is not None:
                ra, rb = find(c), find(d)
                if ra != rb:
                    parent[rb] = ra
    comp_of_cell = {c: find(c) for c in heavy}
    roots = sorted(set(comp_of_cell.values()))
    cand = []
    for r in roots:
        member_cells = [c for c, rr in comp_of_cell.items() if rr == r]
        m = np.isin(inv, member_cells)
        cx, cy, cl = np.median(xl[m]), np.median(yl[m]), np.median(ll[m])
        sx = 1.4826 * np.median(np.abs(xl[m] - cx))
        sy = 1.4826 * np.median(np.abs(yl[m] - cy))
        sl = 1.4826 * np.median(np.abs(ll[m] - cl))
        eps = 1e-3 * h
        cand.append((cx, cy, cl, k_sigma * sx + eps, k_sigma * sy + eps, k_sigma_sum * sl + 1e-3 * sum_step,
                     int(m.sum())))
    dark = ~lit
    if thr > 0 and dark.sum() >= 3:
        # darkness as one more end of a mixture (the sample that straddles an LED's switching on or off)
        dark_end = (float(np.median(x[dark])), float(np.median(y[dark])), math.log(max(float(np.median(s[dark])),
                    1e-300)), 0.0, 0.0, 0.0, int(dark.sum()))
        cand = [c for c in _drop_blends([dark_end] + cand) if c is not dark_end]
    else:
        cand = _drop_blends(cand)
    lab = np.full(idx.size, TRANSITION, dtype=int)
    best = np.full(idx.size, np.inf)
    for j, (cx, cy, cl, tx, ty, tl, _) in enumerate(cand):
        dx, dy, dl = np.abs(xl - cx) / tx, np.abs(yl - cy) / ty, np.abs(ll - cl) / tl
        d = np.maximum(np.maximum(dx, dy), dl)
        take = (d <= 1.0) & (d < best)
        lab[take] = j
        best[take] = d[take]
    # names in the order of the first clean sample
    firsts = [(int(idx[np.flatnonzero(lab == j)[0]]) if np.any(lab == j) else n + j, j) for j in range(len(cand))]
    order = [j for _, j in sorted(firsts) if np.any(lab == j)]
    remap = np.full(len(cand) + 2, TRANSITION)
    for new, j in enumerate(order):
        remap[j] = new
    lab = np.where(lab >= 0, remap[np.clip(lab, 0, None)], lab)
    labels[idx] = lab
    emitters = []
    for k in range(len(order)):
        m = labels == k
        emitters.append(ModuleEmitter(str(k + 1), float(np.median(x[m])), float(np.median(y[m])),
                                      float(np.median(s[m])), float(np.std(x[m], ddof=1)) if m.sum() > 1 else 0.0,
                                      float(np.std(y[m], ddof=1)) if m.sum() > 1 else 0.0, int(m.sum()),
                                      int(np.flatnonzero(m)[0])))
    seg = ModuleSegmentation(labels, tuple(emitters), thr, int((labels == DARK).sum()),
                             int((labels == TRANSITION).sum()))
    if n_emitters is not None and len(emitters) != int(n_emitters):
        raise InputError(
            f"found {len(emitters)} emitters in the module recording, not --n-emitters {n_emitters} "
            f"(positions {', '.join(f'({e.x:.4g}, {e.y:.4g})' for e in emitters[:8])}); refusing to label them",
            field="n_emitters")
    return seg
