"""Target verdicts shared by the benchmark sections.

A verdict is ``(system, contender, kind, value, target[, sense])`` with ``sense`` ``"<="`` (the
default: a ratio or a time that must stay below the target) or ``">="`` (a speedup).
"""

from __future__ import annotations

#: Issue 7: constrained chains at most 1.0x the *best* hand-written baseline (hand Schur or hand
#: augmented LU, whichever is faster in the same run).
TARGET_BEST_HAND = 1.0


def best_hand_verdicts(verdicts):
    """Fold bench_constrained's x(Schur)/x(LU) pairs into one ratio against the faster baseline."""
    out, pairs = [], {}
    for v in verdicts:
        system, name, kind = v[:3]
        if system.startswith("Cartesian") and kind in ("x(Schur)", "x(LU)"):
            pairs.setdefault((system, name), []).append(v[3])
        else:
            out.append(v)
    for (system, name), ratios in pairs.items():
        out.append((system, name, "x(best hand)", max(ratios), TARGET_BEST_HAND))
    return out


def print_verdicts(verdicts):
    print("\ntargets:")
    for v in verdicts:
        system, name, kind, value, target = v[:5]
        sense = v[5] if len(v) > 5 else "<="
        ok = value <= target if sense == "<=" else value >= target
        status = "ok  " if ok else "MISS"
        print(f"  {status} {system:18s} {name:46s} {kind:12s} = {value:7.2f} (target {sense} {target:g})")
