"""Compare s2camp-camp's Gram matrix with CamP's own ``compute_approximate_hessian`` (numpy only).

    .venv/bin/python tools/camp_check/compare.py --ours /tmp/camp_check/ours.npz --camp /tmp/camp_check/camp.npz \
        --write docs/benchmarks/camp-check.md

Both sides estimate E[J^T J] of the same point measure (CamP's published 'frustum_raydist_fn' sampling). Ours is
written in the 13-column split basis (tools/camp_check/ours.py); CamP's in its own 11 flattened parameters. The
chain rule maps ours into CamP's basis: J_camp = J_13 M, so Sigma_camp = M^T Sigma_13 M, with M = d(our deltas) /
d(CamP's parameters) evaluated through CamP's own ``transform_camera`` (tools/camp_check/camp_side.py).

Reported per camera, all relative Frobenius norms against CamP's reference:

- ``ref vs ref``: ours (mapped) against CamP's, both from large samples;
- ``expected``: the Monte-Carlo noise of that difference, from each side's seed-to-seed spread at 5000 points
  scaled by sqrt(5000 / reference points);
- ``MC 5000``: root-mean-square error of 5000-point estimates against their own reference (CamP's and ours), the
  spread the brief asks the agreement to be within;
- ``published``: CamP's J^T J as its training initialises it (PRNGKey(0)) against our reference;
- ``entry``: the largest |difference| of an entry over sqrt(Sigma_ii Sigma_jj) (scale-free, so the small
  intrinsics entries count as much as the pose ones).
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from pathlib import Path

import numpy as np


def fro(a: np.ndarray) -> float:
    return float(np.linalg.norm(a))


def entry_error(a: np.ndarray, reference: np.ndarray) -> float:
    scale = np.sqrt(np.outer(np.diag(reference), np.diag(reference)))
    return float(np.max(np.abs(a - reference) / scale))


def _spd_sqrt(a: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(0.5 * (a + a.T))
    return (vectors * np.sqrt(values)) @ vectors.T


def damping_basis_effect(sigma_13: np.ndarray, mapping: np.ndarray) -> tuple[float, float]:
    """How much CamP's damping, applied in CamP's basis, changes the preconditioned step against ours.

    On the 11 parameters both refine (ours: twist, additive focal, cx, cy, k1, k2; no skew), plain gradient descent
    on whitened parameters moves the camera by -lr (Sigma + D)^-1 g; the Gram part is basis-independent, the
    damping D = diag(max(1e-8, 0.1 diag)) is not. Returns the extreme eigenvalues of
    (Sigma + D_ours)^1/2 (Sigma + D_CamP)^-1 (Sigma + D_ours)^1/2, CamP's damping expressed in our basis; 1 means
    identical steps.
    """
    to_13 = np.zeros((13, 11))
    for k in range(6):
        to_13[k, k] = 1.0
    to_13[6, 6] = to_13[7, 6] = 1.0  # our focal delta adds to fx and fy
    for ours_index, split_index in ((7, 8), (8, 9), (9, 11), (10, 12)):
        to_13[split_index, ours_index] = 1.0
    sigma = to_13.T @ sigma_13 @ to_13
    # CamP's parameters in ours (exact up to the fx / fy ratio of the log focal scale).
    basis = np.linalg.lstsq(to_13, mapping, rcond=None)[0]
    sigma_camp = mapping.T @ sigma_13 @ mapping
    damping_ours = np.diag(np.maximum(1e-8, 0.1 * np.diag(sigma)))
    damping_camp = np.diag(np.maximum(1e-8, 0.1 * np.diag(sigma_camp)))
    inverse = np.linalg.inv(basis)
    root = _spd_sqrt(sigma + damping_ours)
    ratio = root @ np.linalg.inv(sigma + inverse.T @ damping_camp @ inverse) @ root
    values = np.linalg.eigvalsh(0.5 * (ratio + ratio.T))
    return float(values[0]), float(values[-1])


def compare(ours: dict, camp: dict) -> list[dict]:
    rows = []
    for i, name in enumerate(ours["names"]):
        mapping = camp["mapping"][i].astype(np.float64)
        ours_ref = mapping.T @ ours["reference"][i] @ mapping
        camp_ref = camp["reference"][i].astype(np.float64)
        ours_est = [mapping.T @ e @ mapping for e in ours["estimates"][i]]
        camp_est = [e.astype(np.float64) for e in camp["estimates"][i]]
        norm = fro(camp_ref)
        mc_camp = math.sqrt(np.mean([(fro(e - camp_ref) / norm) ** 2 for e in camp_est]))
        mc_ours = math.sqrt(np.mean([(fro(e - ours_ref) / fro(ours_ref)) ** 2 for e in ours_est]))
        n = int(ours["num_points"])
        expected = math.sqrt(
            mc_camp**2 * n / int(camp["reference_points"]) + mc_ours**2 * n / int(ours["reference_points"])
        )
        published = camp["published"][i].astype(np.float64)
        rows.append(
            {
                "camera": str(name),
                "ref_vs_ref": fro(ours_ref - camp_ref) / norm,
                "expected": expected,
                "mc_camp": mc_camp,
                "mc_ours": mc_ours,
                "published": fro(published - ours_ref) / norm,
                "entry_ref": entry_error(ours_ref, camp_ref),
                "entry_mc_camp": math.sqrt(np.mean([entry_error(e, camp_ref) ** 2 for e in camp_est])),
                "within_mc": fro(ours_ref - camp_ref) / norm < min(mc_camp, mc_ours),
                "damping_basis": damping_basis_effect(ours["reference"][i], mapping),
            }
        )
    return rows


def table(rows: list[dict]) -> str:
    header = (
        "| camera | ref vs ref | expected (MC of refs) | MC 5000, CamP | MC 5000, ours "
        "| published (PRNGKey 0) vs our ref | entry, ref vs ref | entry, MC 5000 CamP | within MC 5000 |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    lines = [header]
    for r in rows:
        lines.append(
            f"| {r['camera']} | {r['ref_vs_ref']:.2e} | {r['expected']:.2e} | {r['mc_camp']:.2e} | {r['mc_ours']:.2e} "
            f"| {r['published']:.2e} | {r['entry_ref']:.2e} | {r['entry_mc_camp']:.2e} | "
            f"{'yes' if r['within_mc'] else 'NO'} |"
        )
    return "\n".join(lines)


def damping_table(rows: list[dict]) -> str:
    lines = ["| camera | smallest | largest |", "|---|---|---|"]
    for r in rows:
        low, high = r["damping_basis"]
        lines.append(f"| {r['camera']} | {low:.3g} | {high:.3g} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    within = sum(r["within_mc"] for r in rows)
    to_mc = [r["ref_vs_ref"] / min(r["mc_camp"], r["mc_ours"]) for r in rows]
    to_expected = [r["ref_vs_ref"] / r["expected"] for r in rows]
    return (
        f"Result: ours agrees with CamP's own J^T J within the 5000-point Monte-Carlo spread on {within} of "
        f"{len(rows)} cameras; the reference difference is {min(to_mc):.2g} to {max(to_mc):.2g} times that spread "
        f"and {min(to_expected):.2g} to {max(to_expected):.2g} times the noise the finite references alone "
        "explain (about 1: equal up to the references' own sampling noise)."
    )


def report(rows: list[dict], ours: dict, camp: dict, command: str, previous: list[dict] | None) -> str:
    names = ", ".join(str(p) for p in camp["params"])
    intrinsics = "; ".join(
        f"{n}: fx {v[0]:g}, fy {v[1]:g}, cx {v[2]:g}, cy {v[3]:g}, {v[4]:g} x {v[5]:g}"
        for n, v in zip(ours["names"][::2], ours["intrinsics"][::2], strict=True)
    )
    return "\n".join(
        [
            "# s2camp-camp against CamP's own code",
            "",
            f"Regenerate with the three commands of tools/camp_check/README.md; the last one is `{command}`.",
            "",
            f"_measured {time.strftime('%Y-%m-%d')} on CPU, {platform.machine()}; CamP {camp['delta_class']} at "
            f"commit {camp['camp_commit']} with jax {camp['jax_version']}, jaxcam {camp['jaxcam_version']}_",
            "",
            "Both sides compute E[J^T J] of CamP's published point measure; ours (`CAMP_SAMPLING`, "
            "s2camp_ns/core/camp_sampling.py, our analytic Jacobian in float64) is mapped into CamP's parameters "
            f"({names}) with the chain rule through CamP's own `transform_camera`. References: "
            f"{int(ours['reference_points'])} points (ours), {int(camp['reference_points'])} points (CamP, float32 "
            f"as CamP runs). MC 5000 = root-mean-square relative error of {ours['estimates'].shape[1]} seeds of "
            "5000-point estimates against their own reference. All numbers are relative Frobenius norms against "
            "CamP's reference, except 'entry' (largest |difference| / sqrt(Sigma_ii Sigma_jj)).",
            "",
            f"Cameras: {intrinsics}; each at the identity pose and at a generic world pose (c2w = exp of the twist "
            "(1.2, -0.7, 2.5, 0.3, -0.5, 0.2)), because CamP's SE(3) parameters are the log of the world-to-camera "
            "transform plus a bias, so its J^T J depends on the pose while ours does not.",
            "",
            table(rows),
            "",
            summary(rows),
            "",
            *(
                [
                    "Negative control: the CamP re-implementation this check replaced (uniform random pixel, uniform "
                    "contracted distance in [0.4, 1.99] about the camera centre), same cameras and protocol:",
                    "",
                    table(previous),
                    "",
                ]
                if previous
                else []
            ),
            "What still differs: the parameterisation. s2camp-camp keeps our 12 deltas (the paper compares sampling "
            "strategies, not parameterisations), so CamP's damping diag(max(1e-8, 0.1 diag)) acts in our basis. "
            "The Gram part of a preconditioned step does not depend on the basis, the damping does: the extreme "
            "eigenvalues of (Sigma + D_ours)^1/2 (Sigma + D_CamP)^-1 (Sigma + D_ours)^1/2 on the 11 parameters "
            "both refine (1 = identical plain-gradient steps; Adam's per-coordinate scaling differs further):",
            "",
            damping_table(rows),
            "",
            "At the identity pose CamP's screw parameters are our twist up to order and sign, and the steps agree; "
            "at the generic pose (camera 2.8 units from the world origin) CamP's exp(log T + d) mixes rotation and "
            "translation, and its damping shortens some step directions severalfold. That difference depends on "
            "where the world origin is, which differs between CamP's data pipeline and nerfstudio's dataparser.",
            "",
            "CamP's published configuration as read by gin from configs/camp/camera_optim.gin:",
            "",
            f"`{camp['settings']}`",
            "",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ours", type=Path, required=True)
    parser.add_argument("--camp", type=Path, required=True)
    parser.add_argument("--previous", type=Path, default=None, help="ours.py --previous output (negative control)")
    parser.add_argument("--write", type=Path, default=None, help="markdown report to write")
    args = parser.parse_args()
    ours, camp = dict(np.load(args.ours)), dict(np.load(args.camp))
    if list(ours["names"]) != list(camp["names"]):
        raise SystemExit("--ours and --camp hold different cameras")
    rows = compare(ours, camp)
    print(table(rows))
    previous_rows = None
    if args.previous:
        previous_rows = compare(dict(np.load(args.previous)), camp)
        print("previous re-implementation (negative control):")
        print(table(previous_rows))
    if args.write:
        command = "tools/camp_check/compare.py --ours OURS.npz --camp CAMP.npz --previous PREVIOUS.npz --write " + str(
            args.write
        )
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(report(rows, ours, camp, command, previous_rows))
        print(f"wrote {args.write}")
    if not all(r["within_mc"] for r in rows):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
