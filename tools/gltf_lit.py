"""A lit render of ``flakedb export-openpbr``'s ``.glb`` in three.js (headless Chromium, WebGL 2 on
SwiftShader) and what it shows (docs/renderers.md, the ``.gltf / .glb`` row).

For each ``.glb``: the file and a copy with ``KHR_materials_clearcoat`` removed, each rendered twice
by ``tools/gltf_render/render.mjs`` (three.js's ``GLTFLoader`` and ``MeshPhysicalMaterial``; 288 px,
one sample at each pixel centre, float32 read-back, no tone mapping, linear sRGB):

* *sun*: one ``DirectionalLight`` of irradiance 1 at 35° from the view axis, no environment;
* *furnace*: a uniform environment of radiance 1 (a constant equirect map through three.js's PMREM).

Reported, at the 7 off-highlight pixels of ``test_cycles_matches_preview`` (3 x 3 means of the
32-px grid, whose pixel centres are every 9th of the 288 px render's):

* the coat under the sun: coated / uncoated = 1 - F_c(μ_v) (:func:`flakedb.export.gltf.threejs_coat_fresnel`);
* the coat in the furnace: coated - (1 - F_c(μ_v)) uncoated = the coat's own reflection of the
  uniform sky, against F_c(μ_v) (three.js's Schlick) and the exact F(μ_v; 1.5);
* three.js against what flakedb predicts it renders (:func:`flakedb.export.gltf.threejs_sun_image`)
  and against the fitted model itself (:func:`flakedb.export.blender.model_sun_image`) in ΔE00.

Needs node (≥ 18), Chromium and ``three`` + ``playwright-core`` installed outside the repository::

    npm install --prefix /tmp/gltf-render three@0.187.0 playwright-core@1.65.2
    apt-get install -y chromium
    python tools/gltf_lit.py OUTDIR PAINT.glb [PAINT.glb ...] [--node-modules /tmp/gltf-render/node_modules]

Writes OUTDIR/NAME.{sun,sun-nocoat,furnace,furnace-nocoat}.f32 (288 x 288 x 3 float32, row 0 at the
top) and .png (8-bit sRGB-encoded for viewing, the numbers are from the .f32), and prints a JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from flakedb.colour.tolerance import delta_E_2000
from flakedb.export.blender import model_sun_image, sun_direction
from flakedb.export.gltf import threejs_coat_fresnel, threejs_sun_image
from flakedb.export.openpbr import OpenPBRFit
from flakedb.match.fit import channels_to_Lab
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render.imageio import write_png

RENDER_MJS = Path(__file__).resolve().parent / "gltf_render" / "render.mjs"
DEFAULT_NODE_MODULES = "/tmp/gltf-render/node_modules"
#: The frame: 288 px over [-1.05, 1.05]², so that every 9th pixel centre (from the 5th) is a pixel
#: centre of flakedb's 32-px images (model_sun_image, principled_sun_image)
SIZE, SUB, EXTENT = 288, 9, 1.05
SUN_DEG = 35.0
#: Pixels (row, column) of the 32-px grid compared, 3 x 3 means (tests/export/test_renderers.py::PIXELS)
PIXELS = [(16, 16), (22, 16), (16, 8), (16, 24), (12, 12), (20, 20), (24, 10)]
WL = np.arange(380.0, 781.0, 10.0)


def tools(node_modules: str | None = None) -> tuple[dict | None, str]:
    """({"node", "chromium", "node_modules"}, "") when all three are present, else (None, why)."""
    node = shutil.which("node")
    chromium = os.environ.get("FLAKEDB_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    nm = Path(node_modules or os.environ.get("FLAKEDB_GLTF_NODE_MODULES") or DEFAULT_NODE_MODULES)
    npm = f"three and playwright-core in {nm} (npm install --prefix {nm.parent} three@0.187.0 playwright-core@1.65.2)"
    has_npm = (nm / "three" / "build" / "three.module.js").exists() and (nm / "playwright-core" / "index.mjs").exists()
    missing = [w for w, ok in (("node", node), ("chromium (apt-get install -y chromium)", chromium), (npm, has_npm))
               if not ok]
    if missing:
        return None, "missing: " + "; ".join(missing)
    return {"node": node, "chromium": chromium, "node_modules": str(nm)}, ""


def read_glb(path) -> tuple[dict, bytes]:
    """(JSON document, BIN chunk) of a .glb (glTF 2.0 §4.4)."""
    raw = Path(path).read_bytes()
    magic, _, _ = struct.unpack_from("<III", raw, 0)
    if magic != 0x46546C67:
        raise ValueError(f"{path}: not a .glb (magic {magic:#x})")
    n_json, _ = struct.unpack_from("<II", raw, 12)
    n_bin, _ = struct.unpack_from("<II", raw, 20 + n_json)
    return json.loads(raw[20:20 + n_json]), raw[28 + n_json:28 + n_json + n_bin]


def write_glb(path, doc: dict, blob: bytes) -> Path:
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    blob = blob + b"\0" * (-len(blob) % 4)
    total = 28 + len(js) + len(blob)
    Path(path).write_bytes(struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
                           + struct.pack("<II", len(blob), 0x004E4942) + blob)
    return Path(path)


def without_clearcoat(src, dst) -> Path:
    """A copy of the .glb ``src`` with ``KHR_materials_clearcoat`` removed from its materials and
    ``extensionsUsed``: the same material without its coat."""
    doc, blob = read_glb(src)
    for m in doc.get("materials", []):
        m.get("extensions", {}).pop("KHR_materials_clearcoat", None)
    doc["extensionsUsed"] = [e for e in doc.get("extensionsUsed", []) if e != "KHR_materials_clearcoat"]
    return write_glb(dst, doc, blob)


def fit_of(glb) -> OpenPBRFit:
    return OpenPBRFit.from_dict(read_glb(glb)[0]["materials"][0]["extras"]["flakedb_fit"])


def render(renders: list[dict], tool: dict, timeout: float = 600.0) -> tuple[list[np.ndarray], dict]:
    """Run render.mjs on ``renders`` ({"glb", "sun": {"direction", "irradiance"} | None,
    "environment": L | None}); returns the (SIZE, SIZE, 3) float32 images and the renderer's info."""
    with tempfile.TemporaryDirectory(prefix="flakedb-gltf-") as tmp:
        t = Path(tmp)
        job = {"node_modules": tool["node_modules"], "chromium": tool["chromium"], "user_data_dir": str(t / "profile"),
               "renders": [dict(r, glb=str(Path(r["glb"]).resolve()), out=str(t / f"{i}.f32"), size=SIZE,
                                extent=EXTENT) for i, r in enumerate(renders)]}
        (t / "job.json").write_text(json.dumps(job))
        p = subprocess.run([tool["node"], str(RENDER_MJS), str(t / "job.json")], capture_output=True, text=True,
                           timeout=timeout, check=False)
        if p.returncode != 0:
            tail = "\n".join((p.stdout + p.stderr).strip().splitlines()[-10:])
            raise RuntimeError(f"the three.js render failed (exit {p.returncode}):\n{tail}")
        info = json.loads(p.stdout.strip().splitlines()[-1])
        imgs = [np.fromfile(t / f"{i}.f32", np.float32).reshape(SIZE, SIZE, 3) for i in range(len(renders))]
    return imgs, info


def grid32(img) -> np.ndarray:
    """The 32-px grid's pixel centres of a SIZE-px render."""
    return np.asarray(img, float)[SUB // 2::SUB, SUB // 2::SUB]


def means(img32) -> np.ndarray:
    return np.array([img32[r - 1:r + 2, c - 1:c + 2].reshape(-1, 3).mean(0) for r, c in PIXELS])


def mu_v_means() -> np.ndarray:
    """μ_v at the 3 x 3 pixels around each of PIXELS (7, 9) on the 32-px grid."""
    x = -EXTENT + (np.arange(32) + 0.5) * 2 * EXTENT / 32
    X, Y = np.meshgrid(x, x[::-1])
    mu = np.sqrt(np.clip(1 - X * X - Y * Y, 0, 1))
    return np.array([mu[r - 1:r + 2, c - 1:c + 2].ravel() for r, c in PIXELS])


def lab(m) -> np.ndarray:
    return channels_to_Lab(np.maximum(np.asarray(m) * np.pi, 1e-6), "rgb", WL)


def analyse(fit: OpenPBRFit, sun, sun_bare, furnace, furnace_bare) -> dict:
    """The numbers of the module docstring for one material (images at SIZE px)."""
    d = sun_direction(SUN_DEG)
    mu = mu_v_means()                                                   # (7, 9)
    s, sb = grid32(sun), grid32(sun_bare)
    pix = [(r + i, c + j) for r, c in PIXELS for i in (-1, 0, 1) for j in (-1, 0, 1)]
    rr, cc = np.array(pix).T
    Fc = threejs_coat_fresnel(mu.ravel())
    # channel sums: a channel near 0 (cadmium yellow's blue, 2e-4) is dominated by the coat lobe's tail
    ratio = s[rr, cc].sum(-1) / np.maximum(sb[rr, cc].sum(-1), 1e-30)                 # (63,)
    coat_sun = np.abs(ratio - (1 - Fc)).max()
    f, fb = grid32(furnace), grid32(furnace_bare)
    coat_env = f[rr, cc] - (1 - Fc)[:, None] * fb[rr, cc]              # the coat's reflection of L = 1
    out = {"coat_sun_ratio_minus_1_minus_Fc_max": float(coat_sun),
           "coat_sun_ratio_range": [float(ratio.min()), float(ratio.max())],
           "coat_furnace_minus_Fc_schlick_max": float(np.abs(coat_env - Fc[:, None]).max()),
           "coat_furnace_minus_F_exact_max": float(np.abs(coat_env - fresnel_dielectric(mu.ravel(), 1.5).R[:, None]).max()),
           "coat_furnace_range": [float(coat_env.min()), float(coat_env.max())],
           "coat_furnace_centre": [float(x) for x in f[16, 16] - (1 - threejs_coat_fresnel(mu[0, 4])) * fb[16, 16]]}
    three = means(s)
    model = means(model_sun_image(fit, 32, d))
    out["dE00_three_vs_model"] = [float(x) for x in delta_E_2000(lab(three), lab(model))]
    if fit.thin_film_thickness_nm <= 0:
        pred = means(threejs_sun_image(fit, 32, d, pixel_size=2 * EXTENT / SIZE))
        out["three_vs_prediction_rel_max"] = float(np.abs(three / pred - 1).max())
        out["dE00_prediction_vs_model"] = [float(x) for x in delta_E_2000(lab(pred), lab(model))]
    out["three_over_model"] = [[float(x) for x in row] for row in three / np.maximum(model, 1e-30)]
    return out


def renders_for(glb, bare_glb) -> list[dict]:
    sun = {"direction": list(sun_direction(SUN_DEG)), "irradiance": 1.0}
    return [{"glb": str(glb), "sun": sun, "environment": None}, {"glb": str(bare_glb), "sun": sun, "environment": None},
            {"glb": str(glb), "sun": None, "environment": 1.0}, {"glb": str(bare_glb), "sun": None, "environment": 1.0}]


KINDS = ("sun", "sun-nocoat", "furnace", "furnace-nocoat")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("glb", nargs="+", type=Path)
    ap.add_argument("--node-modules", default=None)
    a = ap.parse_args(argv)
    tool, why = tools(a.node_modules)
    if tool is None:
        print(f"cannot render: {why}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    jobs, names = [], []
    for g in a.glb:
        bare = without_clearcoat(g, a.out / f"{g.stem}.nocoat.glb")
        jobs += renders_for(g, bare)
        names.append(g.stem)
    import time
    t0 = time.perf_counter()
    imgs, info = render(jobs, tool)
    info["render_s"] = round(time.perf_counter() - t0, 1)
    summary = {"renderer": info, "size": SIZE, "extent": EXTENT, "sun_deg": SUN_DEG, "paints": {}}
    for i, (g, name) in enumerate(zip(a.glb, names)):
        four = imgs[4 * i:4 * i + 4]
        for kind, img in zip(KINDS, four):
            img.astype(np.float32).tofile(a.out / f"{name}.{kind}.f32")
            write_png(a.out / f"{name}.{kind}.png", img)
        summary["paints"][name] = analyse(fit_of(g), *four)
    (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
