"""Benchmark: stitch 8 turntable views of tank_t1 (virtual rig truth depth, full
resolution) with prism3d, and Open3D's tutorial pipeline (FPFH + RANSAC +
point-to-plane ICP + pose graph) on the same scans, in the same run.

Usage: python benchmarks/bench_stitch.py [SCENE_DIR]   (default /tmp/stitch_sets/tank8;
rendered once with ``simulate_to_folder("scene", ..., supersample=1)`` when absent).
Prints accuracy (deg, mm), a time breakdown and the time ratio.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

import prism3d  # noqa: F401


def load_scans(folder: Path, stride: int = 1, noise_mm: float = 0.15, dropout: float = 0.1, seed: int = 0):
    from prism3d.capture.rig import StereoRig

    rig = StereoRig.load(folder / "rig.yaml")
    rays = rig.left.pixel_grid_rays()[::stride, ::stride]
    views = json.loads((folder / "poses.json").read_text())["views"]
    rng = np.random.default_rng(seed)
    scans, poses = [], []
    for v in views:
        t = np.load(folder / v["truth"], allow_pickle=False)
        z = t["depth_left_mm"][::stride, ::stride]
        m = np.isfinite(z)
        r = rays[m]
        p = r / r[:, 2:3] * z[m][:, None] + r * rng.normal(0, noise_mm, m.sum())[:, None]
        col = (np.clip(t["albedo_left"][::stride, ::stride][m], 0, 1) * 255).astype(np.uint8)
        keep = rng.random(len(p)) >= dropout
        scans.append((p[keep], col[keep], None))
        poses.append(np.array(v["T_world_cam"]))
    return scans, poses


def errors(Ts, poses, V):
    from prism3d.reconstruct.registration import rotation_angle_deg

    out = []
    for k, T in enumerate(Ts):
        true = np.linalg.inv(poses[0]) @ poses[k]
        Vk = V @ np.linalg.inv(poses[k])[:3, :3].T + np.linalg.inv(poses[k])[:3, 3]
        d = (Vk @ T[:3, :3].T + T[:3, 3]) - (Vk @ true[:3, :3].T + true[:3, 3])
        out.append((rotation_angle_deg(np.linalg.inv(true) @ T), float(np.sqrt(np.mean(np.sum(d**2, 1))))))
    return out


def open3d_tutorial(scans, voxel):
    import open3d as o3d

    reg = o3d.pipelines.registration
    pcs = []
    for p, _, _ in scans:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        pc.orient_normals_towards_camera_location(np.zeros(3))
        pcs.append(pc)
    g = 5 * voxel
    feats, downs = [], []
    for pc in pcs:
        d = pc.voxel_down_sample(g)
        d.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * g, max_nn=30))
        feats.append(reg.compute_fpfh_feature(d, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * g, max_nn=100)))
        downs.append(d)
    graph = reg.PoseGraph()
    odo = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odo))
    n = len(pcs)
    for s in range(n):
        for t in range(s + 1, n):
            if t != s + 1 and not (s == 0 and t == n - 1):
                continue
            r = reg.registration_ransac_based_on_feature_matching(
                downs[s], downs[t], feats[s], feats[t], True, 1.5 * g,
                reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * g)],
                reg.RANSACConvergenceCriteria(100000, 0.999))
            T = r.transformation
            for dist in (3 * voxel, 1.5 * voxel):
                T = reg.registration_icp(pcs[s], pcs[t], dist, T, reg.TransformationEstimationPointToPlane()).transformation
            info = reg.get_information_matrix_from_point_clouds(pcs[s], pcs[t], 1.5 * voxel, T)
            if t == s + 1:
                odo = np.asarray(T) @ odo
                graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odo)))
                graph.edges.append(reg.PoseGraphEdge(s, t, T, info, uncertain=False))
            else:
                graph.edges.append(reg.PoseGraphEdge(s, t, T, info, uncertain=True))
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(),
                            reg.GlobalOptimizationOption(max_correspondence_distance=1.5 * voxel, edge_prune_threshold=0.25,
                                                         reference_node=0))
    return [np.asarray(nd.pose) for nd in graph.nodes]


def main() -> None:
    folder = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/stitch_sets/tank8")
    if not (folder / "poses.json").exists():
        from prism3d.capture.simulate import simulate_to_folder
        from prism3d.datasets.targets import builtin_target

        simulate_to_folder("scene", folder, target=builtin_target("tank_t1"), views=8, seed=1, supersample=1)
    from prism3d.io.ply import read_ply
    from prism3d.reconstruct.stitch import stitch_scans

    scans, poses = load_scans(folder)
    V = read_ply(folder / "target.ply").points
    print(f"8 views, points per view: {[len(s[0]) for s in scans]}")
    for hint in (45.0, None):
        t0 = time.perf_counter()
        res = stitch_scans(scans, turntable_step_deg=hint, mesh=True)
        t_ours = time.perf_counter() - t0
        e = errors(res.T_model_scan, poses, V)
        print(f"prism3d (hint={hint}): {t_ours:.1f} s, breakdown "
              + ", ".join(f"{k} {v:.1f}" for k, v in res.diagnostics["seconds"].items()))
        print(f"  max pose error {max(a for a, _ in e):.4f} deg, max surface motion {max(b for _, b in e):.3f} mm RMS")
    t0 = time.perf_counter()
    Ts = open3d_tutorial(scans, voxel=2 * res.diagnostics["spacing"])
    t_o3d = time.perf_counter() - t0
    e = errors(Ts, poses, V)
    print(f"Open3D tutorial: {t_o3d:.1f} s; max pose error {max(a for a, _ in e):.4f} deg, "
          f"max surface motion {max(b for _, b in e):.3f} mm RMS")
    print(f"ratio prism3d(no hint)/Open3D = {t_ours / t_o3d:.2f}")


if __name__ == "__main__":
    main()
