"""Shared plot for the fitting examples: data vs fitted model, and the loss history."""

from pathlib import Path

import numpy as np


def plot_fit(path, ts, observed, fitted, loss_history, labels, title, extra=None):
    """Save a two-panel PNG; returns the path, or None if matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: skipping the plot (pip install 'jaxlag[examples]')")
        return None
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    observed, fitted = np.asarray(observed), np.asarray(fitted)
    for k, label in enumerate(labels):
        ax1.plot(ts, observed[:, k], ".", ms=3, label=f"{label} observed")
        ax1.plot(ts, fitted[:, k], "-", lw=1, label=f"{label} fitted model")
    if extra is not None:
        extra(ax1)
    ax1.set(xlabel="t", title=title)
    ax1.legend(fontsize=7)
    ax2.semilogy(np.arange(len(loss_history)), loss_history, "o-", ms=3)
    ax2.set(xlabel="optimizer step", ylabel="loss ½Σr²", title="loss history")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print(f"plot written to {path}")
    return path


def report(true, result):
    """Print true vs recovered values with standard errors."""
    for name, value in true.items():
        fitted = float(result.params[name])
        se = float(result.standard_errors[name])
        print(
            f"  {name:>4}: true {value:.6f}   recovered {fitted:.6f} ± {se:.6f}"
            f"   ({(fitted - value) / se:+.2f} standard errors)"
        )
