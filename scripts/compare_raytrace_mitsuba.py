"""Tapestry's `raytrace` method side by side with Mitsuba 3 (llvm_ad_rgb, direct_projective) in
one run: speed, image agreement and gradient error against one finite-difference reference.

usage (the peers' venv, which has mitsuba and numpy; see scripts/bench-raytrace-peers.sh):
  python scripts/compare_raytrace_mitsuba.py --tapestry target/release/tapestry \
      --peers ../shared/peers --out target/bench-raytrace [--threads 2] [--spp 4]

Scenes, 256 x 256:
- ico5k: the peers' icosphere (5120 faces, vertex colours), the peers' camera. Tapestry: shading
  `none`; Mitsuba: `diffuse` with the vertex colours as reflectance under a constant environment
  of radiance 1 (bench_mitsuba.py), so a convex unoccluded surface has radiance = albedo, the same
  image; hide_emitters (black background).
- shadow_dir: a ground plane and a quad occluder in one mesh, Lambert, one directional light of
  colour 1 (Tapestry `albedo * color * max(n . l, 0)`; Mitsuba `directional` with irradiance pi:
  its diffuse BRDF is albedo / pi). A directional light rather than the point light of the tests:
  Tapestry's point light has no falloff (CONVENTIONS), Mitsuba's has 1 / r^2.
- shadow_area: the same, lit by a 0.6 x 0.6 area light of radiance 3 (Mitsuba: a `rectangle` with
  an `area` emitter of radiance 3 pi facing down; both have inverse-square falloff and the
  emitter cosine; the emitter is edge-on to the camera).
No ambient term (Mitsuba's constant emitter would add ambient occlusion).

Loss: L = sum over pixels and RGB of (I - T)^2, T the Tapestry render of the target (ico5k:
ico5k_target.obj; shadow scenes: the occluder moved) at the reference spp. The parameters are a
pose of the moving vertices (the sphere; the occluder): u = (t, r), p -> p + t + (r / R) x
(p - c), c the centroid, R the farthest vertex's distance from it (a unit of each component moves
that vertex by one world unit). Each renderer's vertex gradient is projected onto the pose,
g_u = J^T g_p, and compared with central differences (L(u + h e_k) - L(u - h e_k)) / 2h of
high-spp renders with one seed (common random numbers), h of about half a pixel: cosine and
relative error |g - g_ref| / |g_ref|, mean and spread over seeds. The reference is made with
Tapestry and, with --mitsuba-reference, with Mitsuba too (errors against both are printed).

Images: RMSE between the two renderers' high-spp images against the RMSE between two seeds of
each (the Monte Carlo noise at that spp).

Timings (the same run): forward+backward is the time of the gradient calls above (after one
warm-up call; min and median over the seeds), forward that of --reps renders after a warm-up;
wall-clock and CPU time (user + system of all threads: robust on a shared machine).
Tapestry: in process, `tapestry render` / `tapestry grad --wrt positions` with `--repeat reps`
(f64; the render or gradient only, as Mitsuba's; the whole processes, with start-up, scene and
OBJ parsing and output files, are recorded too as *_process_ms); Mitsuba: in process, bench_mitsuba.py's protocol (float32; forward =
params.update() (BVH rebuild) + render + copy to numpy; fwd+bwd adds dr.backward of L and
reading the vertex gradient). Mitsuba's integrator: direct_projective with sppc = sppp = spp and
sppi = spp for the lit scenes (shadow gradients), 0 for ico5k (bench_mitsuba.py's setting: no
secondary visibility there). Tapestry's edge samples: --edge-samples-per-pixel primary and
shadow-edge samples per pixel (default 1) and --area-edge-samples per pixel sample. Records go
to OUT/compare.jsonl.
"""
import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("--tapestry", required=True)
ap.add_argument("--peers", required=True)
ap.add_argument("--out", required=True)
ap.add_argument("--threads", type=int, default=2)
ap.add_argument("--spp", type=int, default=4)
ap.add_argument("--ref-spp", type=int, default=256)
ap.add_argument("--seeds", type=int, default=3)
ap.add_argument("--reps", type=int, default=5)
ap.add_argument("--scenes", default="ico5k,shadow_dir,shadow_area")
ap.add_argument("--mitsuba-reference", action="store_true")
ap.add_argument("--area-edge-samples", type=int, default=1,
                help="Tapestry's area-light edge samples per pixel sample")
ap.add_argument("--edge-samples-per-pixel", type=int, default=1,
                help="Tapestry's primary and shadow edge samples per pixel (Mitsuba's sppp = spp)")
ap.add_argument("--guiding", default="octree", help="Mitsuba's guiding of indirect discontinuities")
a = ap.parse_args()

os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
sys.path.insert(0, a.peers)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from peers_common import read_obj, write_obj  # noqa: E402

mi.set_variant("llvm_ad_rgb")
dr.set_thread_count(a.threads)
os.makedirs(a.out, exist_ok=True)
W = H = 256
ENV = dict(os.environ, RAYON_NUM_THREADS=str(a.threads))


# ------------------------------------------------------------------------------------------
# scenes
def shadow_mesh():
    V = [(-2, 0, -2), (2, 0, -2), (2, 0, 2), (-2, 0, 2),
         (-0.45, 0.8, -0.25), (0.15, 0.8, -0.2), (0.1, 0.8, 0.25), (-0.4, 0.85, 0.25)]
    C = [(0.8, 0.8, 0.8)] * 4 + [(0.9, 0.3, 0.2)] * 4
    F = [(0, 2, 1), (0, 3, 2), (4, 6, 5), (4, 7, 6)]
    return np.array(V, float), np.array(F, np.int64), np.array(C, float), np.arange(4, 8)


def scene_defs():
    out = {}
    sc = os.path.join(a.peers, "scenes")
    base = json.load(open(os.path.join(sc, "ico5k.json")))
    V, F, C = read_obj(os.path.join(sc, "ico5k.obj"))
    Vt, _, Ct = read_obj(os.path.join(sc, "ico5k_target.obj"))
    out["ico5k"] = dict(V=V, F=F, C=C, Vt=Vt, Ct=Ct, moving=np.arange(len(V)), camera=base["camera"],
                        lights=[], shading="none")
    V, F, C, mv = shadow_mesh()
    Vt = V.copy()
    Vt[mv] += np.array([0.12, 0.0, -0.08])
    cam = {"eye": [0, 3, 2.5], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 45, "near": 0.1, "far": 100}
    out["shadow_dir"] = dict(V=V, F=F, C=C, Vt=Vt, Ct=C, moving=mv, camera=cam, shading="lambert",
                             lights=[{"type": "directional", "direction": [0.25, -1, -0.1], "color": [1, 1, 1]}])
    out["shadow_area"] = dict(V=V, F=F, C=C, Vt=Vt, Ct=C, moving=mv, camera=cam, shading="lambert",
                              lights=[{"type": "area", "corner": [-0.9, 3, -0.3], "edge_u": [0.6, 0, 0],
                                       "edge_v": [0, 0, 0.6], "radiance": [3, 3, 3]}])
    return out


def pose_jacobian(V, moving):
    """J [V*3, 6]: columns t_x, t_y, t_z, r_x, r_y, r_z (rotation per unit of the farthest vertex)."""
    c = V[moving].mean(0)
    R = np.linalg.norm(V[moving] - c, axis=1).max()
    J = np.zeros((V.shape[0], 3, 6))
    for k in range(3):
        J[moving, k, k] = 1.0
        e = np.zeros(3)
        e[k] = 1.0
        J[moving, :, 3 + k] = np.cross(e, V[moving] - c) / R
    return J.reshape(-1, 6)


# ------------------------------------------------------------------------------------------
# Tapestry (CLI processes)
def tap_json(name, s, V, C, spp, seed, tag):
    obj = os.path.join(a.out, f"{name}_{tag}.obj")
    write_obj(obj, V, s["F"], C)
    j = {"mesh": obj, "camera": s["camera"],
         "image": {"width": W, "height": H, "background": [0, 0, 0]},
         "lights": s["lights"], "material": {"shading": s["shading"]},
         "raster": {"method": "raytrace", "spp": spp, "seed": seed,
                    "area_edge_samples": a.area_edge_samples,
                    "edge_samples": a.edge_samples_per_pixel * W * H,
                    "shadow_edge_samples": a.edge_samples_per_pixel * W * H}}
    p = os.path.join(a.out, f"{name}_{tag}_{spp}_{seed}.json")
    json.dump(j, open(p, "w"), indent=1)
    return p


def run_cpu(cmd):
    """Runs cmd; returns (wall ms, CPU ms of the child: user + system, all threads)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=ENV, stdout=subprocess.DEVNULL)
    t1 = time.perf_counter()
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return 1e3 * (t1 - t0), 1e3 * (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime)


def tap_render(js):
    npy = js[:-5] + ".npy"
    subprocess.run([a.tapestry, "render", js, "--out", js[:-5] + ".png", "--npy", npy],
                   check=True, env=ENV, stdout=subprocess.DEVNULL)
    return np.load(npy)[..., :3]


def tap_grad(js, target_npy, times=None):
    g = js[:-5] + "_g.npy"
    t = run_cpu([a.tapestry, "grad", js, "--target", target_npy, "--wrt", "positions", "--out", g])
    if times is not None:
        times.append(t)
    return np.load(g)


def tap_inproc(cmd, reps):
    """In-process timings of a `tapestry render` / `grad` command with `--repeat reps` (no
    start-up, parsing or output files): ([wall min, median], [CPU mean, mean]) in ms."""
    r = subprocess.run(cmd + ["--repeat", str(reps)], check=True, env=ENV,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t = json.loads(r.stderr.strip().splitlines()[-1])
    cpu = t["cpu_ms_mean"] if t["cpu_ms_mean"] is not None else float("nan")
    return [t["wall_ms_min"], t["wall_ms_median"]], [cpu, cpu]


def summary(ts):
    """[min, median] of wall and of CPU times (ms)."""
    w, c = np.array([t[0] for t in ts]), np.array([t[1] for t in ts])
    return [float(w.min()), float(np.median(w))], [float(c.min()), float(np.median(c))]


# ------------------------------------------------------------------------------------------
# Mitsuba
def mi_scene(s, spp):
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse",
                                  "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}})
    m = mi.Mesh("mesh", s["V"].shape[0], s["F"].shape[0], props,
                has_vertex_normals=False, has_vertex_texcoords=False)
    m.add_attribute("vertex_color", 3, mi.Float(s["C"].astype(np.float32).ravel()))
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(s["V"].astype(np.float32).ravel())
    p["faces"] = mi.UInt32(s["F"].astype(np.uint32).ravel())
    p.update()
    cam = s["camera"]
    d = {"type": "scene",
         "integrator": {"type": "direct_projective", "hide_emitters": True,
                        "sppc": spp, "sppp": spp, "sppi": spp if s["lights"] else 0,
                        "guiding": a.guiding},
         "sensor": {"type": "perspective", "fov": float(cam["fov_y_deg"]), "fov_axis": "y",
                    "near_clip": float(cam.get("near", 0.1)), "far_clip": float(cam.get("far", 100)),
                    "to_world": mi.ScalarTransform4f().look_at(origin=cam["eye"], target=cam["at"],
                                                               up=cam.get("up", [0, 1, 0])),
                    "film": {"type": "hdrfilm", "width": W, "height": H,
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"}},
         "mesh": m}
    for i, l in enumerate(s["lights"]):
        if l["type"] == "directional":
            d[f"light{i}"] = {"type": "directional", "direction": l["direction"],
                              "irradiance": {"type": "rgb", "value": [math.pi * c for c in l["color"]]}}
        elif l["type"] == "area":
            eu, ev = np.array(l["edge_u"], float), np.array(l["edge_v"], float)
            n = np.cross(eu, ev)
            n /= np.linalg.norm(n)
            ctr = np.array(l["corner"], float) + 0.5 * (eu + ev)
            M = np.eye(4)
            M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = eu / 2, ev / 2, n, ctr
            d[f"light{i}"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(M.tolist()),
                              "emitter": {"type": "area", "radiance": {
                                  "type": "rgb", "value": [math.pi * c for c in l["radiance"]]}}}
        else:
            raise SystemExit(f"no Mitsuba light for {l['type']}")
    if not s["lights"]:
        d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    return mi.load_dict(d)


class Mi:
    def __init__(self, s, spp):
        self.scene = mi_scene(s, spp)
        self.params = mi.traverse(self.scene)
        self.kV = "mesh.vertex_positions"
        self.spp = spp

    def render(self, V, seed, spp=None):
        self.params[self.kV] = mi.Float(V.astype(np.float32).ravel())
        self.params.update()
        return np.array(mi.render(self.scene, self.params, spp=spp or self.spp, seed=seed))

    def grad(self, V, T, seed):
        v = mi.Float(V.astype(np.float32).ravel())
        dr.enable_grad(v)
        self.params[self.kV] = v
        self.params.update()
        img = mi.render(self.scene, self.params, spp=self.spp, seed=seed)
        loss = dr.sum(dr.square(img - T), axis=None)
        dr.backward(loss)
        return np.array(dr.grad(v), dtype=np.float64).reshape(-1, 3)


# ------------------------------------------------------------------------------------------
def compare(g, ref):
    cos = float(g @ ref / (np.linalg.norm(g) * np.linalg.norm(ref) + 1e-300))
    rel = float(np.linalg.norm(g - ref) / (np.linalg.norm(ref) + 1e-300))
    return cos, rel


def rmse(x, y):
    return float(np.sqrt(np.mean((x - y) ** 2)))


def run(name, s):
    rec = {"scene": name, "res": W, "spp": a.spp, "ref_spp": a.ref_spp, "threads": a.threads,
           "faces": int(s["F"].shape[0])}
    J = pose_jacobian(s["V"], s["moving"])
    # h: about half a pixel at the moving object's distance
    cam = s["camera"]
    dist = np.linalg.norm(s["V"][s["moving"]].mean(0) - np.array(cam["eye"], float))
    h = 0.5 * 2 * dist * math.tan(math.radians(cam["fov_y_deg"]) / 2) / H
    rec["fd_step"] = h
    # target: Tapestry's reference-spp render of the target
    T = tap_render(tap_json(name, s, s["Vt"], s["Ct"], a.ref_spp, 99, "target"))
    tnpy = os.path.join(a.out, f"{name}_T.npy")
    np.save(tnpy, T)
    Tm = mi.TensorXf(T.astype(np.float32))

    def loss(img):
        return float(np.sum((img - T) ** 2))

    # images: both renderers at the reference spp, two seeds each
    mir = Mi(s, a.spp)
    ti = [tap_render(tap_json(name, s, s["V"], s["C"], a.ref_spp, sd, "img")) for sd in (1, 2)]
    mimg = [mir.render(s["V"], sd, a.ref_spp) for sd in (1, 2)]
    rec["image_rmse_tapestry_vs_mitsuba"] = rmse(0.5 * (ti[0] + ti[1]), 0.5 * (mimg[0] + mimg[1]))
    rec["image_rmse_seed_tapestry"] = rmse(ti[0], ti[1])
    rec["image_rmse_seed_mitsuba"] = rmse(mimg[0], mimg[1])
    # expected RMSE of the difference of two 2-seed means if only noise differs
    rec["image_rmse_noise_expected"] = math.sqrt(
        (rec["image_rmse_seed_tapestry"] ** 2 + rec["image_rmse_seed_mitsuba"] ** 2) / 4)
    rec["image_mean_tapestry"] = float(np.mean(ti[0]))
    rec["image_mean_mitsuba"] = float(np.mean(mimg[0]))
    np.save(os.path.join(a.out, f"{name}_tap.npy"), ti[0])
    np.save(os.path.join(a.out, f"{name}_mi.npy"), mimg[0])

    # finite-difference references of the pose gradient
    refs = {}

    def fd(render):
        g = np.zeros(6)
        for k in range(6):
            dV = (J[:, k] * h).reshape(-1, 3)
            g[k] = (loss(render(s["V"] + dV)) - loss(render(s["V"] - dV))) / (2 * h)
        return g

    cnt = [0]

    def tap_at(V):
        cnt[0] += 1
        return tap_render(tap_json(name, s, V, s["C"], a.ref_spp, 5, f"fd{cnt[0]}"))

    refs["tapestry"] = fd(tap_at)
    if a.mitsuba_reference:
        refs["mitsuba"] = fd(lambda V: mir.render(V, 5, a.ref_spp))
        rec["fd_ref_cosine_tapestry_vs_mitsuba"] = compare(refs["mitsuba"], refs["tapestry"])[0]
    rec["fd_ref_tapestry"] = refs["tapestry"].tolist()

    # gradients at a.spp over seeds (one extra first call: warm-up, not counted), timed:
    # fwd+bwd is the time of these calls (one run for speed and error)
    for who in ("tapestry", "mitsuba"):
        gs, ts = [], []
        for sd in range(0, a.seeds + 1):
            if who == "tapestry":
                gp = tap_grad(tap_json(name, s, s["V"], s["C"], a.spp, 100 + sd, "grad"), tnpy, ts)
            else:
                t0, c0 = time.perf_counter(), time.process_time()
                gp = mir.grad(s["V"], Tm, 100 + sd)
                ts.append((1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)))
            if sd > 0:
                gs.append(J.T @ gp.ravel())
        if who == "tapestry":
            # the gradient processes above, whole (start-up, parsing, output file), kept
            # beside the in-process timing that is compared with Mitsuba's in-process calls
            rec["tapestry_fwd_bwd_process_ms"], rec["tapestry_fwd_bwd_process_cpu_ms"] = \
                summary(ts[1:])
            js = tap_json(name, s, s["V"], s["C"], a.spp, 100, "grad")
            rec["tapestry_fwd_bwd_ms"], rec["tapestry_fwd_bwd_cpu_ms"] = tap_inproc(
                [a.tapestry, "grad", js, "--target", tnpy, "--wrt", "positions",
                 "--out", js[:-5] + "_g.npy"], a.reps)
        else:
            rec[f"{who}_fwd_bwd_ms"], rec[f"{who}_fwd_bwd_cpu_ms"] = summary(ts[1:])
        rec[f"grad_{who}"] = [g.tolist() for g in gs]
        for rn, ref in refs.items():
            cr = np.array([compare(g, ref) for g in gs])
            rec[f"{who}_vs_{rn}_fd_cosine"] = [float(cr[:, 0].mean()), float(cr[:, 0].min())]
            rec[f"{who}_vs_{rn}_fd_relerr"] = [float(cr[:, 1].mean()), float(cr[:, 1].max())]

    # forward timings
    js = tap_json(name, s, s["V"], s["C"], a.spp, 0, "time")
    ts = [run_cpu([a.tapestry, "render", js, "--out", js[:-5] + ".png"]) for _ in range(a.reps)]
    rec["tapestry_forward_process_ms"], rec["tapestry_forward_process_cpu_ms"] = summary(ts)
    rec["tapestry_forward_ms"], rec["tapestry_forward_cpu_ms"] = tap_inproc(
        [a.tapestry, "render", js, "--out", js[:-5] + ".png"], a.reps)
    cnt2 = [1000]

    def mfwd():
        cnt2[0] += 1
        mir.render(s["V"], cnt2[0])

    mfwd()
    ts = []
    for _ in range(a.reps):
        t0, c0 = time.perf_counter(), time.process_time()
        mfwd()
        ts.append((1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)))
    rec["mitsuba_forward_ms"], rec["mitsuba_forward_cpu_ms"] = summary(ts)
    rec["mitsuba"] = "mitsuba %s / drjit %s, llvm_ad_rgb, direct_projective sppc=sppp=spp, sppi=%s, guiding %s" % (
        mi.__version__, dr.__version__, "spp" if s["lights"] else 0, a.guiding)
    rec["area_edge_samples"] = a.area_edge_samples
    rec["edge_samples_per_pixel"] = a.edge_samples_per_pixel
    return rec


defs = scene_defs()
with open(os.path.join(a.out, "compare.jsonl"), "a") as fh:
    for name in a.scenes.split(","):
        r = run(name, defs[name])
        fh.write(json.dumps(r) + "\n")
        fh.flush()
        f = lambda x: "%.0f" % x[0]  # noqa: E731
        print(f"{name}: forward tapestry {f(r['tapestry_forward_ms'])} ms / mitsuba {f(r['mitsuba_forward_ms'])} ms; "
              f"fwd+bwd tapestry {f(r['tapestry_fwd_bwd_ms'])} ms / mitsuba {f(r['mitsuba_fwd_bwd_ms'])} ms (wall, min)",
              flush=True)
        print(f"  CPU: forward tapestry {f(r['tapestry_forward_cpu_ms'])} ms / mitsuba {f(r['mitsuba_forward_cpu_ms'])} ms; "
              f"fwd+bwd tapestry {f(r['tapestry_fwd_bwd_cpu_ms'])} ms / mitsuba {f(r['mitsuba_fwd_bwd_cpu_ms'])} ms "
              f"(user + system, all threads; Tapestry: mean)", flush=True)
        print(f"  whole Tapestry processes: forward {f(r['tapestry_forward_process_ms'])} ms, "
              f"fwd+bwd {f(r['tapestry_fwd_bwd_process_ms'])} ms (wall, min)", flush=True)
        print(f"  image RMSE tapestry-mitsuba {r['image_rmse_tapestry_vs_mitsuba']:.4f} "
              f"(noise alone: {r['image_rmse_noise_expected']:.4f}); means {r['image_mean_tapestry']:.4f} / "
              f"{r['image_mean_mitsuba']:.4f}", flush=True)
        for rn in ["tapestry", "mitsuba"]:
            k = f"tapestry_vs_{rn}_fd_relerr"
            if k in r:
                print(f"  vs {rn} FD: tapestry cos {r[f'tapestry_vs_{rn}_fd_cosine'][0]:.3f} "
                      f"rel err {r[k][0]:.3f}; mitsuba cos {r[f'mitsuba_vs_{rn}_fd_cosine'][0]:.3f} "
                      f"rel err {r[f'mitsuba_vs_{rn}_fd_relerr'][0]:.3f} (mean of {a.seeds} seeds)", flush=True)
