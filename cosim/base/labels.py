"""How the workbench names things in file names and in prose: the one definition of each label.

* :func:`period_label` -- a control period in file names: ``1ms``, ``13p33us``;
* :func:`period_text` -- the same period in tables, titles and text: ``1 ms``, ``13.33 µs`` (``13.33 us`` in
  ASCII, the benchmark table's);
* :func:`slug` -- any label reduced to lower-case letters, digits and dashes for file names;
* :data:`MIN_PERIOD` -- the shortest period (control, record, communication step) taken for one, not a unit slip.
"""

from __future__ import annotations

import math
import re

#: the shortest control or record period accepted [s]: 100 ns, far below any digital controller's sample period (one
#: switching period of the paper's converter is 13.3 us). A shorter one is almost surely a unit slip (ns for us) and
#: would make tens of millions of steps that fill the memory before anything is written.
MIN_PERIOD = 1e-7


def period_too_short(what: str) -> str:
    """The refusal of a period below :data:`MIN_PERIOD`, ``what`` naming it and its value."""
    return (f"{what} is invalid: expected >= {MIN_PERIOD:g} s (one switching period of the paper's converter is "
            "13.3 us): was it given in another unit?")


def _whole_milliseconds(period: float) -> int | None:
    """The period in ms if it is a whole number of them (>= 1 ms), else None."""
    if period >= 1e-3 and math.isclose(period * 1e3, round(period * 1e3), rel_tol=1e-9):
        return round(period * 1e3)
    return None


def period_label(period: float) -> str:
    """Short file-name label of a control period [s]: ``1ms``, ``13p33us``."""
    ms = _whole_milliseconds(period)
    return f"{ms}ms" if ms is not None else f"{period * 1e6:.4g}us".replace(".", "p")


def period_text(period: float, ascii_only: bool = False) -> str:
    """A control period [s] as text: ``1 ms``, ``2.5 ms``, ``13.33 µs`` (``13.33 us`` with ``ascii_only``, as the
    benchmark table names its rows)."""
    if period >= 1e-3:
        return f"{period * 1e3:.4g} ms"
    return f"{period * 1e6:.4g} {'us' if ascii_only else 'µs'}"


def slug(text: str) -> str:
    """``"MPC-oracle (sync. sample)"`` -> ``"mpc-oracle-sync-sample"``."""
    return re.sub(r"[^A-Za-z0-9]+", "-", text).strip("-").lower()


def did_you_mean(name: str, candidates, hint_all: int = 0) -> str:
    """A hint for a mistyped ``name``: `` (did you mean 'x'?)`` naming the closest of ``candidates``
    (difflib, case-insensitive), else -- with ``hint_all`` > 0 and at most that many candidates --
    `` (expected one of a, b, c)``, else ``""``."""
    import difflib

    candidates = list(dict.fromkeys(str(c) for c in candidates))
    lowered = {c.lower(): c for c in candidates}
    close = difflib.get_close_matches(str(name).lower(), list(lowered), n=1, cutoff=0.6)
    if close:
        return f" (did you mean {lowered[close[0]]!r}?)"
    if candidates and len(candidates) <= hint_all:
        return f" (expected one of {', '.join(candidates)})"
    return ""
