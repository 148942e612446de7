"""The CPU peer OpenSplat 1.1.5 for bench/peers.py: its input folder, its runs and its renders.

OpenSplat (pierotofy/OpenSplat, AGPL-3.0) is run as an outside program, never vendored; its build
and the facts a fair comparison needs are in ../shared/peers/opensplat/README.md. What this module
relies on, read from its source (commit 15b7e80):
- input: a nerfstudio folder (transforms.json: fl_x, fl_y, cx, cy, w, h, frames[].file_path and
  transform_matrix camera-to-world in OpenGL axes, ply_file_path = initial points);
- it normalises the poses (tensor_math.cpp autoScaleAndCenterPoses): centre = mean camera origin,
  scale = 1 / max |origin - centre| over every coordinate, no rotation; `--keep-crs` writes its
  PLY back in the input's frame (means / scale + centre, log scales - log scale);
- its CPU path ignores cx, cy: the principal point is the image centre ((W-1)/2, (H-1)/2 with
  pixel centres at integers), so the images are cropped to centre it (`principal_point_crop`);
- its CPU rasterizer sorts by `pProj[:, 2]`, a stride-3 view read as if contiguous: Gaussian g is
  composited in the order of pProj.flat[2 + g] (a neighbour's normalised-device x, y or z,
  computed in its normalised frame), so a correct 3D-GS renderer does not draw its images;
  `render_native` reproduces them (checked against its --val-render images by the reference
  harness at 52.8 dB, the uint8 limit), `render_standard` is a correct 3D-GS rendering of its PLY;
- colours: its SH basis and signs (spherical_harmonics.cpp), degree min(step // 1000, 3) with
  step the iteration in the PLY header, then max(. + 0.5, 0); background (0.6130, 0.0101, 0.3984);
- it prints "Step N: loss (P%)" after every step on the CPU and, with --save-every K,
  writes OUT_N.ply after steps K, 2K, ...
"""
from __future__ import annotations

import json
import re
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

BACKGROUND = (0.6130, 0.0101, 0.3984)  # model.hpp: nerfstudio's default, fixed
SH_INTERVAL, SH_DEGREE = 1000, 3  # its --sh-degree-interval and --sh-degree defaults
FLOATS_PER_GAUSSIAN = 3 + 3 + 4 + 1 + 3 * 16  # means, log-scales, quaternion, opacity, SH degree 3
C0, C1 = 0.28209479177387814, 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)  # fmt: skip
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes x right, y down, z forward -> y up, z back


@dataclass(frozen=True)
class Crop:
    """Pixels cut from each side so that the principal point is the image centre."""

    top: int
    bottom: int
    left: int
    right: int

    def apply(self, image: np.ndarray) -> np.ndarray:
        """[H,W,...] -> [H - top - bottom, W - left - right, ...]."""
        h, w = image.shape[:2]
        return image[self.top : h - self.bottom, self.left : w - self.right]


def principal_point_crop(cx: float, cy: float, width: int, height: int) -> Crop:
    """The crop that centres (cx, cy) (OpenCV convention, pixel centres at integers) to within
    half a pixel: 2 cx - (W - 1) columns off the left when positive, off the right otherwise."""
    dx, dy = int(round(2 * cx - (width - 1))), int(round(2 * cy - (height - 1)))
    return Crop(top=max(dy, 0), bottom=max(-dy, 0), left=max(dx, 0), right=max(-dx, 0))


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Initial points: xyz [N,3] float, rgb [N,3] in [0,1] (stored as uchar)."""
    from plyfile import PlyData, PlyElement

    rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    u8 = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    rec["red"], rec["green"], rec["blue"] = u8[:, 0], u8[:, 1], u8[:, 2]
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(path))


def write_input(folder: Path, camera: dict, crop: Crop, views: list[tuple[int, np.ndarray, np.ndarray]], xyz: np.ndarray,
                rgb: np.ndarray) -> dict:  # fmt: skip
    """OpenSplat's input folder: images/NNNNN.png (cropped uint8), points.ply, transforms.json.

    camera: {"fx", "fy", "cx", "cy", "width", "height"} of the uncropped frames; views: (frame
    index, image [H,W,3] uint8 RGB, w2c [4,4]) of every training view. Returns (centre, scale) of
    its pose normalisation as {"centre": [3], "scale": float}."""
    import cv2

    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for idx, image, w2c in views:
        name = f"images/{idx:05d}.png"
        cv2.imwrite(str(folder / name), cv2.cvtColor(np.ascontiguousarray(crop.apply(image)), cv2.COLOR_RGB2BGR))
        c2w = np.linalg.inv(np.asarray(w2c, dtype=np.float64)) @ OPENCV_TO_OPENGL
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    write_points_ply(folder / "points.ply", xyz, rgb)
    w, h = camera["width"] - crop.left - crop.right, camera["height"] - crop.top - crop.bottom
    transforms = {"camera_model": "OPENCV", "fl_x": camera["fx"], "fl_y": camera["fy"], "cx": camera["cx"] - crop.left,
                  "cy": camera["cy"] - crop.top, "w": w, "h": h, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames,
                  "ply_file_path": "points.ply"}  # fmt: skip
    (folder / "transforms.json").write_text(json.dumps(transforms, indent=1))
    origins = np.array([f["transform_matrix"] for f in frames], dtype=np.float32)[:, :3, 3]
    centre = origins.mean(0)
    return {"centre": centre.tolist(), "scale": float(np.float32(1.0) / np.abs(origins - centre).max())}


# -- runs ---------------------------------------------------------------------------------------
STEP_LINE = re.compile(r"Step (\d+): ")


def run(binary: str, folder: Path, iterations: int, out: Path, env: dict, save_every: int = 0) -> dict:
    """Train `iterations` steps with its default schedule (--keep-crs), timed from launch.

    Returns {"iterations", "wall_s" (launch -> last step), "process_s", "steps": [[seconds since
    launch, step], ...] (every printed step), "snapshots": {step: path}, "peak_rss_mb", "cpu_pct",
    "ply"}; /usr/bin/time -v gives the peak RSS."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = ["/usr/bin/time", "-v", "-o", str(out / "time.txt"), binary, str(folder), "-n", str(iterations), "--keep-crs",
           "-o", str(out / "splat.ply")] + (["--save-every", str(save_every)] if save_every else [])  # fmt: skip
    steps: list[list[float]] = []
    launch = time.perf_counter()
    with open(out / "log.txt", "w") as log, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                                             env=env, bufsize=1) as proc:  # fmt: skip
        for line in proc.stdout:
            t = time.perf_counter() - launch
            m = STEP_LINE.match(line)
            if m:
                steps.append([t, int(m.group(1))])
            log.write(f"{t:.3f} {line}")
    if proc.returncode != 0 or not steps:
        raise RuntimeError(f"OpenSplat failed (exit {proc.returncode}); its log: {out / 'log.txt'}")
    snaps = {s: out / f"splat_{s}.ply" for s in range(save_every, iterations, save_every)} if save_every else {}
    return {"iterations": iterations, "wall_s": steps[-1][0], "process_s": time.perf_counter() - launch, "steps": steps,
            "snapshots": {s: str(p) for s, p in snaps.items() if p.exists()}, "ply": str(out / "splat.ply"),
            **gnu_time(out / "time.txt")}  # fmt: skip


def gnu_time(path: Path) -> dict:
    """/usr/bin/time -v: {"peak_rss_mb" (10^6 bytes, as segs reports), "cpu_pct"}."""
    text = path.read_text()
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1))
    cpu = re.search(r"Percent of CPU this job got: (\d+)%", text)
    return {"peak_rss_mb": rss_kb * 1024 / 1e6, "cpu_pct": int(cpu.group(1)) if cpu else None}


def seconds_at(steps: list[list[float]], step: int) -> float:
    """Seconds since launch at which `step` was printed."""
    return next(t for t, s in steps if s >= step)


# -- renders ------------------------------------------------------------------------------------
def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """[N,(degree+1)^2] real SH basis of unit directions [N,3] in OpenSplat's order and signs."""
    x, y, z = dirs.unbind(-1)
    b = [torch.full_like(x, C0)]
    if degree >= 1:
        b += [C1 * -y, C1 * z, C1 * -x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        b += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        b += [C3[0] * y * (3 * xx - yy), C3[1] * xy * z, C3[2] * y * (4 * zz - xx - yy), C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
              C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]  # fmt: skip
    return torch.stack(b, -1)


class PeerModel:
    """An OpenSplat PLY written with --keep-crs (the input's frame), and its renders.

    frame: {"centre", "scale"} of its pose normalisation (write_input's return)."""

    def __init__(self, ply: Path | str, frame: dict):
        from plyfile import PlyData

        data = PlyData.read(str(ply))
        v = data["vertex"].data
        col = lambda *ks: torch.from_numpy(np.stack([np.asarray(v[k], np.float32) for k in ks], -1))  # noqa: E731
        rest = sorted((n for n in v.dtype.names if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
        n = len(v)
        dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None]
        rest_t = col(*rest).reshape(n, 3, -1).transpose(1, 2) if rest else torch.zeros(n, 0, 3)
        self.coeffs = torch.cat([dc, rest_t], 1)  # [N,16,3]
        step = next((int(m.group(1)) for c in data.comments if (m := re.search(r"iteration (\d+)", c))), 0)
        self.step, self.n = step, n
        self.degree = min(step // SH_INTERVAL, SH_DEGREE, int(round(self.coeffs.shape[1] ** 0.5)) - 1)
        self.means = col("x", "y", "z")
        self.scales = torch.exp(col("scale_0", "scale_1", "scale_2"))
        self.quats = col("rot_0", "rot_1", "rot_2", "rot_3")
        self.opacities = torch.sigmoid(torch.from_numpy(np.asarray(v["opacity"], np.float32)))
        # a diverged run can write nan / inf rows: they draw nothing in its own renderer, so they are left out (counted)
        finite = torch.stack([t.reshape(n, -1).isfinite().all(1) for t in
                              (self.means, self.scales, self.quats, self.opacities, self.coeffs)]).all(0)  # fmt: skip
        self.non_finite = int((~finite).sum())
        if self.non_finite:
            self.means, self.scales, self.quats = self.means[finite], self.scales[finite], self.quats[finite]
            self.opacities, self.coeffs, self.n = self.opacities[finite], self.coeffs[finite], int(finite.sum())
        self.centre, self.scale = torch.tensor(frame["centre"], dtype=torch.float32), float(frame["scale"])

    def model_mb(self) -> float:
        """Its parameters in MB (float32)."""
        return self.n * FLOATS_PER_GAUSSIAN * 4 / 1e6

    def _colors(self, cam_centre: torch.Tensor) -> torch.Tensor:
        dirs = self.means - cam_centre
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        k = (self.degree + 1) ** 2
        return ((sh_basis(dirs, self.degree)[..., None] * self.coeffs[:, :k]).sum(1) + 0.5).clamp_min(0.0)

    def render_standard(self, w2c: np.ndarray, camera: dict) -> torch.Tensor:
        """[H,W,3] a correct 3D-GS rendering (segs.raster, sorted by depth) at the true camera."""
        from segs.raster import rasterize

        w2c_t = torch.as_tensor(w2c, dtype=torch.float32)
        K = torch.tensor([[camera["fx"], 0.0, camera["cx"] + 0.5], [0.0, camera["fy"], camera["cy"] + 0.5], [0.0, 0.0, 1.0]])
        out = rasterize(self.means, self.quats, self.scales, self.opacities, self._colors(_cam_centre(w2c_t)), w2c_t, K,
                        camera["width"], camera["height"], background=torch.tensor(BACKGROUND), backend="cpu")  # fmt: skip
        return out.image.clamp(0, 1)

    def render_native(self, w2c: np.ndarray, camera: dict) -> torch.Tensor:
        """[H,W,3] what its own CPU renderer draws at this camera: a canvas centred on the principal
        point (its renderer's only one), cut to the frame, composited in its sort order."""
        from segs.raster import _cpu_backend

        w, h, cx, cy = camera["width"], camera["height"], camera["cx"], camera["cy"]
        w2, x0 = _canvas(cx, w)
        h2, y0 = _canvas(cy, h)
        w2c_t = torch.as_tensor(w2c, dtype=torch.float32)
        centre = _cam_centre(w2c_t)
        fx, fy = camera["fx"], camera["fy"]
        # its sort key, in its normalised frame, float32 as there
        pv = ((self.means - self.centre) * self.scale - (centre - self.centre) * self.scale) @ w2c_t[:3, :3].T
        z = pv[:, 2].clamp_min(1e-6)
        near, far = 0.001, 1000.0
        pproj = torch.stack([(2 * fx / w2) * pv[:, 0] / z, (2 * fy / h2) * pv[:, 1] / z,
                             ((far + near) / (far - near) * pv[:, 2] - 2 * far * near / (far - near)) / z], -1)  # fmt: skip
        key = pproj.reshape(-1)[2 : 2 + self.n]
        rank = torch.empty(self.n)
        rank[torch.argsort(key, stable=True)] = torch.arange(1, self.n + 1, dtype=torch.float32)
        K = torch.tensor([[fx, 0.0, w2 / 2.0], [0.0, fy, h2 / 2.0], [0.0, 0.0, 1.0]])
        proj = _cpu_backend.project(self.means, self.quats, self.scales, w2c_t, K, w2, h2, 0.01, 100.0)
        image, _, _ = _cpu_backend.rasterize_pixels(proj.means2d, proj.conics, self._colors(centre), self.opacities, rank,
                                                    proj.radii, w2, h2, torch.tensor(BACKGROUND))  # fmt: skip
        return image[y0 : y0 + h, x0 : x0 + w].clamp(0, 1)


def _cam_centre(w2c: torch.Tensor) -> torch.Tensor:
    return torch.linalg.inv(w2c.double())[:3, 3].float()


def _canvas(c: float, size: int) -> tuple[int, int]:
    """(canvas size, offset of the frame in it) for a principal point at c of a `size`-pixel axis:
    the canvas is centred on c and holds the frame."""
    if c >= (size - 1) / 2:
        return int(round(2 * c + 1)), 0
    full = int(round(2 * (size - 1 - c) + 1))
    return full, full - size
