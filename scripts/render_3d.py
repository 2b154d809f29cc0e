"""The README's pictures, as a user gets them in QGIS desktop: the pipeline's layers and a new 3D map view.

    xvfb-run is called by this script itself (QGIS's 3D engine needs OpenGL, which
    QT_QPA_PLATFORM=offscreen does not give; Xvfb gives Mesa's llvmpipe):

    .venv/bin/python scripts/render_3d.py [--input resources/sample/sample.laz] [--out-dir resources/screenshots]

Starts QGIS desktop under Xvfb with ``scripts/desktop_outputs.py``, which runs
``sylva:pipeline`` from its dialog (Run pressed, as a user would), lets
Processing load the run's layers with Sylva's styles, saves the 2D map
(``crowns_2d.png``: the crowns, graduated by height, over the CHM), opens
*View ▸ New 3D Map View* and grabs it with the camera that view starts with
(``trees_3d.png``), grabs it again with ``crowns_3d`` hidden, then with ``models_3d`` hidden too, then runs
``sylva:exportmodels`` from its dialog and grabs a new 3D view of its layers.

Prints the share of the 3D view's pixels that are trees (the bark colour of
``resources/styles/models_3d.qml``, red > green > blue, or the crown colour of
``crowns_3d.qml``, green > red > blue: see :func:`tree_pixels`), with the
crowns hidden, and with both 3D layers hidden.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DESKTOP_SCRIPT = ROOT / "scripts" / "desktop_outputs.py"
SCREEN = "1600x1000x24"


def pixels(png: Path) -> np.ndarray:
    """(h, w, 3) uint8 RGB of a PNG (QImage when QGIS's Qt is there, else Pillow)."""
    try:
        from qgis.PyQt.QtGui import QImage
    except ImportError:  # pragma: no cover - without QGIS
        from PIL import Image

        return np.asarray(Image.open(png).convert("RGB")).copy()
    image = QImage(str(png)).convertToFormat(QImage.Format_RGB888)
    if image.isNull():
        raise ValueError(f"{png} is not an image")
    h, w = image.height(), image.width()
    ptr = image.constBits()
    ptr.setsize(image.bytesPerLine() * h)
    rows = np.frombuffer(ptr, dtype=np.uint8).reshape(h, image.bytesPerLine())[:, :3 * w]
    return rows.reshape(h, w, 3).copy()


def bark_pixels(rgb: np.ndarray) -> np.ndarray:
    """Pixels of the models' bark (models_3d.qml: diffuse 139,90,43, Phong-shaded): red > green > blue by
    clear margins."""
    r, g, b = (rgb[..., i].astype(np.int32) for i in range(3))
    return (r > g + 8) & (g > b + 4) & (r - b > 30) & (r < 230)


def crown_pixels(rgb: np.ndarray) -> np.ndarray:
    """Pixels of the 3D crowns (crowns_3d.qml: diffuse 70,120,24, ambient 64,110,24, Phong-shaded): in the
    light a saturated yellow green (red about 0.55 and blue about 0.2 of green), in the shade a dark green
    with next to no blue (about 15,45,4 under QGIS 3.22's default light).  The 2D map's greens (crowns.qml's
    yellow-green ramp, half transparent; tree_tops.qml and its dark outline 11,61,11) are paler or bluer."""
    r, g, b = (rgb[..., i].astype(np.int32) for i in range(3))
    lit = (g > 40) & (g < 250) & (100 * r > 40 * g) & (100 * r < 72 * g) & (100 * b < 40 * g)
    shade = (g >= 32) & (b <= 8) & (2 * r < g)
    return lit | shade


def tree_pixels(rgb: np.ndarray) -> np.ndarray:
    """Pixels of trees in a 3D view: bark (:func:`bark_pixels`) or crowns (:func:`crown_pixels`).  The maps
    under them (greys, the crowns' greens, white) have neither colour."""
    return bark_pixels(rgb) | crown_pixels(rgb)


def tree_share(png: Path) -> float:
    return float(tree_pixels(pixels(png)).mean())


def crop_margins(png: Path, out: Path, pad: int = 4) -> Path:
    """Copy ``png`` without its empty margins (the map canvas's background colour, its corner pixel)."""
    from qgis.PyQt.QtGui import QImage

    rgb = pixels(png).astype(np.int32)
    content = np.abs(rgb - rgb[0, 0]).max(axis=2) > 6
    rows, cols = np.flatnonzero(content.any(axis=1)), np.flatnonzero(content.any(axis=0))
    image = QImage(str(png))
    if len(rows) and len(cols):
        r0, c0 = max(rows[0] - pad, 0), max(cols[0] - pad, 0)
        r1, c1 = min(rows[-1] + pad, rgb.shape[0] - 1), min(cols[-1] + pad, rgb.shape[1] - 1)
        image = image.copy(int(c0), int(r0), int(c1 - c0 + 1), int(r1 - r0 + 1))
    image.save(str(out))
    return out


def desktop_session(sample: Path, workdir: Path, timeout_s: float = 1200.0, stall_s: float = 360.0) -> dict:
    """Run scripts/desktop_outputs.py in QGIS desktop under Xvfb; returns its report (with ``shots``).

    The session writes its report after every step.  When no step ends for ``stall_s`` seconds the session
    is killed and run once more from the start, and the report says so (``attempts``): Qt3D 5.15 in QGIS 3.22
    now and then deadlocks while it creates a 3D view (the main thread waits in
    ``QAspectEngine::setRootEntity`` for the render thread, which waits for it), which no timer inside the
    frozen application can end.  One cause is known and avoided: a Python QgsTask running meanwhile (the
    plugin's warm-up, on a first load after ``core/`` changed) holds a pooled thread waiting for the GIL,
    which the main thread holds there; ``desktop_outputs.py`` opens its 3D views once no task runs."""
    if shutil.which("xvfb-run") is None or shutil.which("qgis") is None:
        raise RuntimeError("needs xvfb-run and qgis (Debian: apt-get install -y xvfb qgis)")
    workdir.mkdir(parents=True, exist_ok=True)
    shots = workdir / "shots"
    report_path = workdir / "report.json"
    env = {k: v for k, v in os.environ.items() if k != "QT_QPA_PLATFORM"}   # the desktop needs the X display
    purelib = sysconfig.get_paths()["purelib"]     # the venv's packages for QGIS's Python
    env.update(QGIS_PLUGINPATH=str(ROOT / ".qgis-plugins"), PROJ_DATA=env.get("PROJ_DATA", "/usr/share/proj"),
               PYTHONPATH=os.pathsep.join(p for p in (purelib, env.get("PYTHONPATH", "")) if p),
               SYLVA_REPORT=str(report_path), SYLVA_SAMPLE=str(sample), SYLVA_OUT=str(workdir / "forest"),
               SYLVA_SHOTS=str(shots))
    env.setdefault("XDG_RUNTIME_DIR", f"/tmp/runtime-{os.getuid()}")
    Path(env["XDG_RUNTIME_DIR"]).mkdir(mode=0o700, exist_ok=True)
    cmd = ["xvfb-run", "-a", "-s", f"-screen 0 {SCREEN}", "qgis", "--profiles-path", str(ROOT / ".qgis-profile"),
           "--nologo", "--noversioncheck", "--code", str(DESKTOP_SCRIPT)]
    stalls = []
    for attempt in (1, 2):
        shutil.rmtree(workdir / "forest", ignore_errors=True)   # a stalled attempt's files go
        shutil.rmtree(shots, ignore_errors=True)
        report_path.unlink(missing_ok=True)
        shots.mkdir()
        returncode, stalled = _run_watched(cmd, env, workdir, timeout_s, stall_s, report_path)
        if not stalled:
            break
        stalls.append(stalled)
    report = json.loads(report_path.read_text()) if report_path.exists() else {"error": "no report"}
    report.update(returncode=returncode, shots=str(shots), log=str(workdir / "qgis.log"), attempts=attempt,
                  stalls=stalls)
    return report


def _run_watched(cmd, env, workdir: Path, timeout_s: float, stall_s: float, report_path: Path):
    """(return code, None) of the session, or (None, the last step it finished) when it stalled."""
    import signal

    with open(workdir / "qgis.log", "ab") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=workdir,
                                start_new_session=True)
        start = last = time.monotonic()
        seen = None
        while proc.poll() is None:
            time.sleep(1.0)
            stamp = report_path.stat().st_mtime if report_path.exists() else None
            if stamp != seen:
                seen, last = stamp, time.monotonic()
            now = time.monotonic()
            if now - last > stall_s or now - start > timeout_s:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                if now - start > timeout_s:
                    raise subprocess.TimeoutExpired(cmd, timeout_s)
                try:
                    steps = json.loads(report_path.read_text()).get("steps", [])
                except (OSError, ValueError):
                    steps = []
                return None, steps[-1][1] if steps else "start"
    return proc.returncode, None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", type=Path, default=ROOT / "resources" / "sample" / "sample.laz")
    ap.add_argument("--out-dir", type=Path, default=ROOT / "resources" / "screenshots")
    ap.add_argument("--keep", type=Path, help="keep the run and every screenshot in this folder")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="sylva-desktop-") as tmp:
        work = args.keep or Path(tmp)
        start = time.perf_counter()
        report = desktop_session(args.input.resolve(), work)
        # an abort after the last step is QGIS 3.22 tearing down Qt3D at exit, not a failed session
        if report.get("error") or not report.get("steps") or report["steps"][-1][1] != "done":
            sys.exit(f"render_3d: the desktop session failed: {report.get('error')} (log: {report['log']})")
        shots = Path(report["shots"])
        args.out_dir.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shots / "view3d_pipeline.png", args.out_dir / "trees_3d.png")
        crop_margins(shots / "crowns_2d.png", args.out_dir / "crowns_2d.png")
        rgb = pixels(shots / "view3d_pipeline.png")
        print(f"{args.out_dir / 'trees_3d.png'}: {rgb.shape[1]} x {rgb.shape[0]} px, QGIS 3D view with the camera of "
              f"a new view: {100 * tree_share(shots / 'view3d_pipeline.png'):.1f} % of the pixels are trees "
              f"({100 * tree_share(shots / 'view3d_pipeline_no_crowns.png'):.1f} % with crowns_3d hidden, "
              f"{100 * tree_share(shots / 'view3d_pipeline_no_models.png'):.2f} % with both 3D layers hidden); "
              f"after exportmodels alone: {100 * tree_share(shots / 'view3d_exportmodels.png'):.1f} %")
        print(f"{args.out_dir / 'crowns_2d.png'}: the pipeline's layers as loaded by its dialog: "
              + ", ".join(f"{layer['name']} ({layer['renderer'] or 'table'})" for layer in report["layers"]))
        print(f"desktop session {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
