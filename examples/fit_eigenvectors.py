"""Fit a quad mesh so that its low eigenvalues AND eigenvectors match a target's.

    python examples/fit_eigenvectors.py [--n 10] [--k 6] [--steps 60] [--out examples/output]

A regular ``n x n`` quad grid on the rectangle ``[0, 1] x [0, 0.7]``
(``torch_polylap.shapes.quad_grid``) is moved by Adam so that
the first ``k`` non-constant eigenpairs of ``L phi = mu M0 phi`` (this package's polygon
Laplacian, AW11) match those of a target with the same connectivity: the grid bent by a smooth
planar warp. The loss is

    sum_i (mu_i / mu*_i - 1)^2  +  sum_i (1 - |phi_i^T M0 phi*_i| / |phi*_i|_M0)

The second term is one minus the cosine between each eigenvector and its target in the current
mass inner product (``phi_i^T M0 phi_i = 1``); it does not depend on the sign of either vector
(a convention), and its gradient reaches the vertices through the eigenvector derivatives of
``tp.eigs`` (one sparse factorization of ``L - mu_i M0`` per eigenpair and step). Prints the
loss going down; writes a short report (loss history, fitted vertices) to
``examples/output/fit_eigenvectors.md`` and a figure (the loss, and the initial, target and
fitted grids) to ``fit_eigenvectors.png`` there. The spectrum does not see rigid motions, so
the fitted grid matches the target up to one.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import torch_polylap as tp
from torch_polylap.shapes import quad_grid


def warp(verts: torch.Tensor) -> torch.Tensor:
    """A smooth planar deformation: a bend in x and a taper in y."""
    x, y, z = verts.unbind(1)
    return torch.stack([x + 0.12 * torch.sin(np.pi * y / 0.7), y * (1.0 + 0.35 * x), z], 1)


def spectrum(verts: torch.Tensor, faces: torch.Tensor, k: int):
    """``(mu, phi, M0)``: the eigenpairs 1..k (the constant pair 0 left out) and the mass."""
    L, M0 = tp.laplacian(verts, faces)
    evals, evecs = tp.eigs(L, M0, k + 1)
    return evals[1:], evecs[:, 1:], M0


def loss_terms(verts, faces, k, target_mu, target_phi):
    mu, phi, M0 = spectrum(verts, faces, k)
    value_term = ((mu / target_mu - 1.0) ** 2).sum()
    # cosine in the current mass inner product (phi^T M0 phi = 1): at most 1, scale-invariant
    target_m = M0 @ target_phi
    cosine = (phi * target_m).sum(0).abs() / (target_phi * target_m).sum(0).sqrt()
    vector_term = (1.0 - cosine).sum()
    return value_term, vector_term


def fit(n: int, k: int, steps: int, lr: float, log_every: int) -> dict:
    verts, faces = quad_grid(n, extent=(0.0, 1.0, 0.0, 0.7))
    with torch.no_grad():
        target_mu, target_phi, _ = spectrum(warp(verts), faces, k)
    X = verts.clone().requires_grad_(True)
    optimizer = torch.optim.Adam([X], lr=lr)
    history = []
    start = time.perf_counter()
    for step in range(steps + 1):
        value_term, vector_term = loss_terms(X, faces, k, target_mu, target_phi)
        loss = value_term + vector_term
        history.append((step, loss.item(), value_term.item(), vector_term.item()))
        if step % log_every == 0 or step == steps:
            print(
                f"step {step:4d}  loss {loss.item():.6f}  eigenvalues {value_term.item():.6f}  "
                f"eigenvectors {vector_term.item():.6f}",
                flush=True,
            )
        if step == steps:
            break
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - start
    with torch.no_grad():
        mu, _, _ = spectrum(X, faces, k)
    print(
        f"{steps} steps in {seconds:.1f} s; loss {history[0][1]:.6f} -> {history[-1][1]:.6f}; "
        f"largest eigenvalue error {(mu / target_mu - 1).abs().max().item():.2e} (relative)"
    )
    return {
        "history": history,
        "initial": verts,
        "target": warp(verts),
        "verts": X.detach(),
        "faces": faces,
        "seconds": seconds,
    }


def report(result: dict, args: argparse.Namespace) -> str:
    lines = [
        "# Fitting eigenvalues and eigenvectors",
        "",
        f"`python examples/fit_eigenvectors.py --n {args.n} --k {args.k} --steps {args.steps}` "
        f"({result['seconds']:.1f} s)",
        "",
        "| step | loss | eigenvalue term | eigenvector term |",
        "|---|---|---|---|",
    ]
    stride = max(1, len(result["history"]) // 10)
    rows = result["history"][::stride] + ([result["history"][-1]] if stride > 1 else [])
    for step, loss, values, vectors in dict.fromkeys(rows):
        lines.append(f"| {step} | {loss:.6f} | {values:.6f} | {vectors:.6f} |")
    lines += ["", "Fitted vertices (x y z):", "", "```"]
    lines += [" ".join(f"{c:.6f}" for c in v) for v in result["verts"].tolist()]
    return "\n".join(lines + ["```", ""])


def figure(result: dict, path: Path) -> None:
    """The loss terms over the steps, and the initial, target and fitted grids (the fitted one
    moved rigidly onto the target, which the spectrum cannot see)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps, loss, values, vectors = (list(c) for c in zip(*result["history"], strict=True))
    verts, faces = result["verts"], result["faces"]
    target = result["target"]
    fitted = procrustes(verts, target)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.semilogy(steps, loss, label="loss")
    left.semilogy(steps, values, label="eigenvalue term")
    left.semilogy(steps, vectors, label="eigenvector term")
    left.set_xlabel("Adam step")
    left.legend()
    grids = (
        ("initial", result["initial"], "0.6"),
        ("target", target, "C0"),
        ("fitted", fitted, "C3"),
    )
    for label, X, color in grids:
        xy = X[:, :2].numpy()
        for face in faces.tolist():
            ring = xy[face + face[:1]]
            right.plot(ring[:, 0], ring[:, 1], color=color, lw=0.8)
        right.plot([], [], color=color, label=label)
    right.set_aspect("equal")
    right.legend(loc="upper left", fontsize=8)
    right.set_title("grids (fitted: moved rigidly onto the target)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def procrustes(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """``X`` moved by the rotation and translation that bring it closest to ``Y``."""
    cx, cy = X.mean(0), Y.mean(0)
    U, _, Vt = torch.linalg.svd((X - cx).T @ (Y - cy))
    d = torch.sign(torch.linalg.det(U @ Vt))
    D = torch.diag(torch.tensor([1.0, 1.0, float(d)], dtype=X.dtype))
    return (X - cx) @ (U @ D @ Vt) + cy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10, help="quads per side of the grid")
    parser.add_argument("--k", type=int, default=6, help="non-constant eigenpairs to match")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--lr", type=float, default=0.01)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent / "output", help="folder"
    )
    args = parser.parse_args()
    torch.set_default_dtype(torch.float64)
    result = fit(args.n, args.k, args.steps, args.lr, log_every=max(1, args.steps // 10))
    args.out.mkdir(parents=True, exist_ok=True)
    md, png = args.out / "fit_eigenvectors.md", args.out / "fit_eigenvectors.png"
    md.write_text(report(result, args), encoding="utf-8")
    figure(result, png)
    print(f"wrote {md} and {png}")


if __name__ == "__main__":
    main()
