"""The measurement behind docs/decisions/027-web-viewer.md: viser or rerun for the web viewer.

    python bench/viewer_library.py [--rerun-path DIR] [--repeats 5]

For each library: the import time (median of --repeats fresh interpreters, interleaved, less an
empty interpreter's), and whether and how fast the same 20,000 Gaussian splats appear in
Debian's headless Chromium (software WebGL, no GPU) driven by playwright: seconds from opening the
page to the first screenshot whose centre is coloured (the splats, not the page's grey / white). rerun-sdk is not a dependency of
this project: install it aside (`pip install --target DIR rerun-sdk`) and pass --rerun-path DIR.
"""
from __future__ import annotations

import argparse
import io
import os
import statistics
import subprocess
import sys
import time

import _harness

_harness.apply_process_settings()  # before torch loads

import numpy as np

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]  # fmt: skip
N = 20_000


def import_seconds(module: str, path: str | None, repeats: int) -> float:
    """Median wall seconds of `import module` in a fresh interpreter, less an empty one's."""
    env = {**os.environ, **({"PYTHONPATH": path} if path else {})}
    run = lambda code: _time([sys.executable, "-c", code], env)  # noqa: E731
    base, full = [], []
    for _ in range(repeats):
        base.append(run("pass"))
        full.append(run(f"import {module}"))
    return statistics.median(full) - statistics.median(base)


def _time(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, capture_output=True)
    return time.perf_counter() - t0


def splats() -> tuple[np.ndarray, np.ndarray]:
    """20,000 Gaussians in a unit ball: centres [N,3], colours [N,3] in [0,1]."""
    c = np.random.default_rng(0).normal(size=(N, 3)).astype(np.float32)
    return c, np.clip(c * 0.3 + 0.5, 0, 1)


def serve_viser() -> str:
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=8731, verbose=False)
    c, rgb = splats()
    server.scene.add_gaussian_splats("/splats", centers=c, covariances=np.tile(np.eye(3, dtype=np.float32) * 0.003, (N, 1, 1)),
                                     rgbs=rgb, opacities=np.full((N, 1), 0.8, np.float32))  # fmt: skip
    server.initial_camera.position, server.initial_camera.look_at = (0.0, -6.0, 0.0), (0.0, 0.0, 0.0)
    return f"http://127.0.0.1:{server.get_port()}/"


def serve_rerun() -> str:
    import rerun as rr

    rr.init("segs_viewer_library")
    uri = rr.serve_grpc(grpc_port=9877)
    rr.serve_web_viewer(web_port=9090, open_browser=False, connect_to=uri)
    c, rgb = splats()
    rgba = np.concatenate([(rgb * 255).astype(np.uint8), np.full((N, 1), 204, np.uint8)], 1)
    rr.log("splats", rr.GaussianSplats3D(centers=c, scales=np.full((N, 3), 0.055, np.float32),
                                         quaternions=np.tile([0, 0, 0, 1.0], (N, 1)).astype(np.float32), colors=rgba))  # fmt: skip
    return f"http://127.0.0.1:9090/?url={uri}"


def seconds_to_splats(url: str, timeout: float = 120.0) -> float | None:
    """Seconds from opening url to a screenshot whose centre shows the splats (None: never)."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        page = browser.new_page(viewport={"width": 800, "height": 600})
        t0 = time.perf_counter()
        page.goto(url)
        while time.perf_counter() - t0 < timeout:
            image = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64)[200:400, 300:500]
            if np.abs(image.mean(axis=(0, 1)) - image.mean()).max() > 15:  # coloured: the splats, not the grey / white page
                seconds = time.perf_counter() - t0
                break
            page.wait_for_timeout(250)
        else:
            seconds = None
        browser.close()
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rerun-path", help="a folder holding rerun-sdk (pip install --target DIR rerun-sdk)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--library", choices=("viser", "rerun"), help=argparse.SUPPRESS)  # one library's browser check
    args = parser.parse_args()
    if args.library:  # in a fresh interpreter: the library's server and the browser
        print(seconds_to_splats(serve_viser() if args.library == "viser" else serve_rerun()))
        os._exit(0)  # the servers' threads do not end by themselves
    for name, module, path in (("viser", "viser", None), ("rerun", "rerun", args.rerun_path)):
        if name == "rerun" and not path:
            print("rerun: skipped (no --rerun-path)")
            continue
        env = {**os.environ, **({"PYTHONPATH": path} if path else {})}
        res = subprocess.run([sys.executable, __file__, "--library", name], env=env, capture_output=True, text=True, timeout=600)
        last = res.stdout.strip().splitlines()[-1] if res.stdout.strip() else None
        shown = f"{float(last):.1f}" if last not in (None, "None") else f"never ({res.stderr.strip()[-200:]})"
        print(f"{name}: import {import_seconds(module, path, args.repeats):.2f} s; 20,000 splats in headless Chromium after "
              f"{shown} s")


if __name__ == "__main__":
    main()
