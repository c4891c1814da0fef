"""`adjust-calibrate`: an anipose ``calibration.toml`` from known 3D points and their 2D images.

    adjust-calibrate input.points3d=lockbox.csv input.points2d=labels/ output.dir=out \
        input.size=[1280,1024] [input.intrinsics=calibration.toml] [resection.fit_dist=[k1]]

The paper's calibration from the lock box (eq. 1-2): points whose 3D positions are known (the
box's corners, its mechanisms; a CSV ``name,x,y,z`` in mm) and their pixel positions in each
camera (a CSV ``name,u,v`` per camera, the camera named by the file's stem; or a DeepLabCut
labels file per camera, its parts being the point names, one labelled image). Each camera is
found by spatial resection (`adjust.resection.resect`): with unknown intrinsics a normalized DLT
then Levenberg-Marquardt over focal lengths, principal point, pose (and the distortion terms in
``resection.fit_dist``) -- at least 6 points, not all in one plane; with ``input.intrinsics``
(an existing calibration whose K and distortion are kept) a PnP pose -- at least 4 points.

Writes ``calibration.toml`` (anipose layout, `adjust.io.save_calibration`) and
``summary.json``: per camera the points used, the rms and largest reprojection error (px), the
camera centre (mm, world) and the intrinsics. Too few points, points in one plane (without
intrinsics), an unknown camera or point name is a one-line error naming the file.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from adjust.apps.common import finite_or_none, hydra_app, prepare_output
from adjust.camera import Camera, CameraTensors, project_cameras
from adjust.io import InputError, load_calibration, read_dlc, save_calibration
from adjust.resection import resect
from adjust.settings import required, setting
from deformnet.atomic import write_text
from deformnet.paths import regular_file

log = logging.getLogger(__name__)


def read_points_csv(path: str | Path, coords: tuple[str, ...]) -> dict[str, np.ndarray]:
    """A CSV with a header ``name`` plus `coords` (e.g. x,y,z or u,v; case-insensitive; for
    2D also x,y) -> {name: (len(coords),) float64}. Empty coordinate cells: the point is not
    visible (left out)."""
    path = regular_file(path, "points file", InputError)  # a FIFO or device: never opened
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read CSV: {exc}") from None
    if not rows:
        raise InputError(f"{path}: empty file")
    header = [c.strip().lower() for c in rows[0]]
    want = list(coords)
    if len(coords) == 2 and not set(want) <= set(header) and {"x", "y"} <= set(header):
        want = ["x", "y"]
    missing = [c for c in ["name", *want] if c not in header]
    if missing:
        raise InputError(
            f"{path}: header {rows[0]} lacks columns {missing} (expected name,{','.join(coords)})"
        )
    idx = [header.index(c) for c in ["name", *want]]
    out: dict[str, np.ndarray] = {}
    for line, row in enumerate(rows[1:], start=2):
        if len(row) < len(header):
            raise InputError(f"{path}: line {line} has {len(row)} cells, the header {len(header)}")
        name = row[idx[0]].strip()
        cells = [row[i].strip() for i in idx[1:]]
        if not name:
            raise InputError(f"{path}: line {line}: empty point name")
        if name in out:
            raise InputError(f"{path}: line {line}: point '{name}' appears twice")
        if all(c == "" for c in cells):
            continue  # not visible
        try:
            v = np.array([float(c) for c in cells])
        except ValueError:
            raise InputError(f"{path}: line {line}: non-numeric coordinates {cells}") from None
        if not np.isfinite(v).all():
            raise InputError(f"{path}: line {line}: non-finite coordinates {cells}")
        out[name] = v
    if not out:
        raise InputError(f"{path}: no points")
    return out


def _read_2d(path: Path) -> dict[str, np.ndarray]:
    """One camera's 2D points: a name,u,v CSV or a DeepLabCut labels file (one image)."""
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        first = fh.readline().split(",")[0].strip().lower()
    if first != "scorer" and path.suffix.lower() == ".csv":
        return read_points_csv(path, ("u", "v"))
    table = read_dlc(path)
    rows = np.isfinite(table.xy).all(-1).any(-1)
    if rows.sum() != 1:
        raise InputError(
            f"{path}: a DeepLabCut labels file for calibration must label one image; it labels "
            f"{int(rows.sum())}"
        )
    r = int(np.flatnonzero(rows)[0])
    return {
        p: table.xy[r, k] for k, p in enumerate(table.parts) if np.isfinite(table.xy[r, k]).all()
    }


def _project(X: np.ndarray, cam: Camera) -> np.ndarray:
    """(N, 2) pixels of points X (N, 3) in one camera."""
    ct = CameraTensors.from_cameras([cam], dtype=torch.float64)
    with torch.no_grad():
        return project_cameras(torch.as_tensor(X), ct)[:, 0].numpy()


def _files(folder: Path, cameras) -> dict[str, Path]:
    if not folder.is_dir():
        raise InputError(f"input.points2d: folder not found: {folder}")
    files = sorted(
        f
        for f in folder.iterdir()
        if f.is_file() and not f.name.startswith(".") and f.suffix.lower() in (".csv", ".h5")
    )
    by_stem = {f.stem: f for f in files}
    if cameras:
        names = [str(c) for c in cameras]
        chosen = {}
        for n in names:
            hits = [f for f in files if n in f.stem]
            hits = [f for f in hits if f.stem == n] or hits
            if len(hits) != 1:
                raise InputError(
                    f"{folder}: camera '{n}' matches {len(hits)} files "
                    f"({[f.name for f in hits]}); one file per camera, its name in the file name"
                )
            chosen[n] = hits[0]
        return chosen
    if not by_stem:
        raise InputError(f"{folder}: no 2D point files (.csv, .h5)")
    return by_stem


def run(cfg: DictConfig) -> dict:
    """Resect every camera, write calibration.toml and summary.json; returns the summary."""

    p3 = required(cfg, "input.points3d", "calibrate")
    p2 = Path(required(cfg, "input.points2d", "calibrate"))
    inp, res_cfg = cfg.input, cfg.get("resection") or {}
    fit_skew = setting(cfg, "resection.fit_skew", "bool", False)
    max_error = setting(cfg, "resection.max_error_px", "float", 5.0, lo=0.0)
    fit_dist = [str(k) for k in (res_cfg.get("fit_dist") or [])]
    size = inp.get("size")
    known: dict[str, Camera] = {}
    if inp.get("intrinsics"):
        known = {c.name: c for c in load_calibration(str(inp.intrinsics))}
    elif size is None:
        raise InputError(
            "set input.size=[width,height] (the cameras' image size, px) or "
            "input.intrinsics=calibration.toml"
        )
    if size is not None:
        try:
            size = (int(size[0]), int(size[1]))
            assert len(inp.size) == 2 and size[0] > 0 and size[1] > 0
        except (TypeError, ValueError, IndexError, AssertionError):
            raise InputError(f"input.size must be [width, height] > 0 px, got {size!r}") from None
    out = prepare_output(cfg)
    world = read_points_csv(p3, ("x", "y", "z"))
    files = _files(p2, inp.get("cameras"))
    if known:
        unknown = [n for n in files if n not in known]
        if unknown:
            raise InputError(
                f"{inp.intrinsics}: no intrinsics for cameras {unknown} (it has {list(known)})"
            )
    cameras, report = [], {}
    for name, f in files.items():
        image = _read_2d(f)
        stray = sorted(set(image) - set(world))
        if stray:
            raise InputError(f"{f}: points {stray} are not in {p3} (known points: {sorted(world)})")
        names = [n for n in world if n in image]
        X = np.array([world[n] for n in names]).reshape(-1, 3)
        x = np.array([image[n] for n in names]).reshape(-1, 2)
        prior = known.get(name)
        try:
            cam = resect(
                X,
                x,
                K=None if prior is None else prior.K,
                dist=None if prior is None else prior.dist,
                name=name,
                size=size if prior is None or size is not None else prior.size,
                fit_skew=fit_skew,
                fit_dist=fit_dist,
                fisheye=prior is not None and prior.fisheye,
            )
        except ValueError as exc:
            raise InputError(f"{f} (camera '{name}', {len(names)} points): {exc}") from None
        err = np.linalg.norm(_project(X, cam) - x, axis=-1)
        depth = X @ cam.R[2] + cam.tvec[2]
        if (depth <= 0).any():
            raise InputError(
                f"{f} (camera '{name}'): the resected camera has {int((depth <= 0).sum())} "
                "points behind it: the 2D positions do not fit the 3D points (mislabelled?)"
            )
        rms = float(np.sqrt(np.mean(err**2)))
        worst = names[int(np.argmax(err))]
        if rms > max_error:
            log.warning(
                "camera '%s' (%s): rms reprojection error %.2f px > %.1f px (worst point '%s' "
                "%.1f px): a mislabelled point?",
                name,
                f,
                rms,
                max_error,
                worst,
                float(err.max()),
            )
        cam.extra.clear()  # resect's diagnostics go to the summary, not the calibration
        cameras.append(cam)
        report[name] = {
            "file": str(f),
            "points": len(names),
            "rms_px": rms,
            "max_px": float(err.max()),
            "worst_point": worst,
            "center_mm": cam.center.tolist(),
            "focal_px": [float(cam.K[0, 0]), float(cam.K[1, 1])],
            "principal_point_px": [float(cam.K[0, 2]), float(cam.K[1, 2])],
            "distortion": cam.dist.tolist(),
        }
        log.info(
            "camera '%s': %d points, rms %.2f px, max %.2f px; centre %s mm",
            name,
            len(names),
            rms,
            float(err.max()),
            np.round(cam.center, 1).tolist(),
        )
    meta = {"source": "adjust-calibrate", "points3d": str(Path(p3).resolve())}
    cal = save_calibration(out / "calibration.toml", cameras, meta)
    summary = finite_or_none(
        {
            "inputs": {"points3d": str(Path(p3).resolve()), "points2d": str(p2.resolve())},
            "intrinsics": "given" if known else "fitted",
            "fit_dist": fit_dist,
            "cameras": report,
            "outputs": {"calibration": str(cal), "summary": str(out / "summary.json")},
        }
    )
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


main = hydra_app(run, "calibrate")


if __name__ == "__main__":  # pragma: no cover
    main()
