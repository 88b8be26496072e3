"""Load benchmark of the nodes: a 30 Hz camera stream into sfm_node + segmentation_node.

A drone camera at ``--fps`` publishes ``--size`` images with poses for ``--duration`` seconds.
Rendering 3,600 frames at 1280x720 is out of reach on 2 cores, so ``--unique`` views are
rendered along the simulated orbit and each is held (same image, same pose) until the next:
like a drone that hovers between waypoints, the keyframe selector sees enough motion only when
the view changes. Reported: frames published / received / dropped (by reason), keyframes
selected and processed, images decoded (only keyframe candidates should be), SfM seconds per
keyframe, latencies from a keyframe's image to (a) the OOI cloud segmented from the SfM cloud
that includes it, (b) its first mask (provisional while no full run covered it) and (c) its
final mask (the full run that covers it) -- for the last keyframe of the flight and as median
/ max over all keyframes -- keyframe evictions and the bytes of kept keyframe images, and
resident memory sampled every second (bounded queues and a byte budget: it must level off).
``--budget-mb`` sets the segmentation node's ``image_budget_mb`` (default: the node's own) to
watch eviction at work.

Side by side, in the same process: the same stream into a bare subscriber that only counts
(what the transport itself delivers), as the baseline.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_nodes_load.py --duration 120
"""

from __future__ import annotations

import argparse
import os
import pickle
import resource
import threading
import time

import numpy as np
import psutil
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from ooi_seg_ros import msgconv
from ooi_seg_ros.nodes.common import (latched_qos, limit_heap_growth, mask_is_provisional,
                                      reliable_qos, sensor_qos)
from ooi_seg_ros.nodes.segmentation_node import SegmentationNode
from ooi_seg_ros.nodes.sfm_node import SfmNode
from ooi_seg_ros.sim import simulate_capture


def stream(capture, fps, duration, pubs, stats, stop):
    """Publishes the held views at ``fps`` on (info, pose, image) publishers."""
    info_pub, pose_pub, img_pub = pubs
    views = capture.views
    n = int(duration * fps)
    t0 = time.monotonic()
    base_ns = 1_800_000_000 * 10 ** 9
    msgs = [(msgconv.rgb_to_image(v.get_image(), msgconv.ns_to_stamp(0), "cam"),
             msgconv.intrinsics_to_camera_info(v.camera, msgconv.ns_to_stamp(0), "cam"), v)
            for v in views]
    for i in range(n):
        if stop.is_set():
            break
        due = t0 + i / fps
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        else:
            stats["late"] = stats.get("late", 0) + 1
        vi = min(int(i / n * len(views)), len(views) - 1)
        img, info, v = msgs[vi]
        stats.setdefault("view_of", {})[base_ns + int(i * 1e9 / fps)] = vi
        stamp = msgconv.ns_to_stamp(base_ns + int(i * 1e9 / fps))
        img.header.stamp = stamp
        info.header.stamp = stamp
        pose_pub.publish(msgconv.pose_to_pose_stamped(v.pose, stamp, "map"))
        info_pub.publish(info)
        img_pub.publish(img)
        stats["published"] = stats.get("published", 0) + 1
        stats.setdefault("pub_time", {})[base_ns + int(i * 1e9 / fps)] = time.monotonic()


def run_case(capture, fps, duration, with_nodes: bool, budget_mb: float = 0.0,
             fast_path: bool = True, seg_params: tuple = ()) -> dict:
    ctx = Context()
    rclpy.init(context=ctx)
    ns = "/load_nodes" if with_nodes else "/load_base"
    feeder = Node("feeder", context=ctx, namespace=ns)
    pubs = (feeder.create_publisher(CameraInfo, "camera_info", sensor_qos()),
            feeder.create_publisher(PoseStamped, "pose", sensor_qos()),
            feeder.create_publisher(Image, "image", sensor_qos()))
    nodes = [feeder]
    got = {"images": 0, "ooi": [], "mask": {}, "sfm": {},  # mask: stamp -> arrival times
           "mask_provisional": {}}
    if with_nodes:
        sfm = SfmNode(context=ctx, namespace=ns)
        seg = SegmentationNode(context=ctx, namespace=ns, parameter_overrides=[
            Parameter("image_budget_mb", value=float(budget_mb)),
            Parameter("provisional_masks", value=fast_path),
            Parameter("cloud_runs", value=fast_path)] + list(seg_params))
        nodes += [sfm, seg]
        feeder.create_subscription(PointCloud2, "ooi/points",
                                   lambda m: got["ooi"].append((time.monotonic(), m)),
                                   latched_qos())

        feeder.create_subscription(  # first arrival of the SfM cloud of each newest keyframe
            PointCloud2, "sfm/points", lambda m: got["sfm"].setdefault(
                msgconv.stamp_to_ns(m.header.stamp), time.monotonic()), latched_qos())

        def on_mask(m):  # arrival times of each keyframe's masks, IoU vs the ground truth
            t = time.monotonic()
            k = msgconv.stamp_to_ns(m.header.stamp)
            got["mask"].setdefault(k, []).append(t)
            # which of a keyframe's masks were provisional, in arrival order (the kind travels
            # in the message's frame_id)
            got["mask_provisional"].setdefault(k, []).append(mask_is_provisional(m))
            vi = stats.get("view_of", {}).get(k)
            gt = capture.views[vi].gt_mask if vi is not None else None
            if gt is not None:
                pred = msgconv.image_to_mask(m)
                inter = float((pred & gt).sum())
                got.setdefault("iou", {}).setdefault(k, []).append(
                    inter / max((pred | gt).sum(), 1))
                got.setdefault("recall", {}).setdefault(k, []).append(inter / max(gt.sum(), 1))

        feeder.create_subscription(Image, "ooi/mask", on_mask, reliable_qos(100))
    else:
        feeder.create_subscription(Image, "image",
                                   lambda m: got.__setitem__("images", got["images"] + 1),
                                   sensor_qos())
    ex = MultiThreadedExecutor(num_threads=4, context=ctx)
    for n in nodes:
        ex.add_node(n)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    time.sleep(1.0)
    proc = psutil.Process()
    rss: list[float] = []
    stats: dict = {}
    stop = threading.Event()
    pub_thread = threading.Thread(target=stream, args=(capture, fps, duration, pubs, stats,
                                                       stop), daemon=True)
    t0 = time.monotonic()
    load0, cpu0 = os.getloadavg()[0], time.process_time()
    pub_thread.start()
    rss_kids: list[float] = []  # worker processes (SfM features, segmentation runs)
    kid_cpu: dict = {}  # pid -> CPU seconds last seen (a worker may end before the stream)

    def kids_rss() -> float:
        tot = 0.0
        for c in proc.children(recursive=True):
            try:
                tot += c.memory_info().rss
                ct = c.cpu_times()
                kid_cpu[c.pid] = ct.user + ct.system
            except psutil.Error:
                pass
        return tot / 2 ** 20

    while pub_thread.is_alive():
        rss.append(proc.memory_info().rss / 2 ** 20)
        rss_kids.append(kids_rss())
        time.sleep(1.0)
    out = {"published": stats.get("published", 0), "late_publishes": stats.get("late", 0),
           "rss_mb_first": rss[1] if len(rss) > 1 else None,
           "rss_mb_mid": rss[len(rss) // 2] if rss else None,
           "rss_mb_last": rss[-1] if rss else None,
           "rss_mb_quartiles": [round(rss[min(len(rss) - 1, len(rss) * q // 4)])
                                for q in (1, 2, 3, 4)] if rss else None}
    if with_nodes:
        # let SfM and the last segmentation finish, then measure latency
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and (
                sfm.keyframes_processed + sfm.diag.counters.get("dropped_backlog", 0)
                + sfm.diag.counters.get("error_sfm", 0) < sfm.selector.accepted):
            time.sleep(0.5)
        t_done_sfm = time.monotonic()
        # the node re-segments by itself (every_n_keyframes, or idle_run_s after the last
        # input): wait for the run that includes the newest keyframe
        last_kf = max(int(k) for k in seg.keyframes) if seg.keyframes else None
        while time.monotonic() < deadline and (seg.last_run_newest_ns != last_kf
                                               or seg._busy.locked()):
            time.sleep(0.2)
        time.sleep(2.0)  # the masks of the last run
        pub = stats["pub_time"]
        sfm_last = msgconv.stamp_to_ns(seg._points_msg.header.stamp) if seg._points_msg \
            else None
        ooi = [(t, msgconv.stamp_to_ns(m.header.stamp)) for t, m in got["ooi"]]
        kf_stamps = sorted(k for k in got["mask"] if k in pub)

        def cloud_latency(k):  # first OOI cloud from an SfM cloud that includes keyframe k
            ts = [t for t, st in ooi if st >= k]
            return min(ts) - pub[k] if ts else None

        def sfm_latency(k):  # first SfM cloud that includes keyframe k
            ts = [t for st, t in got["sfm"].items() if st >= k]
            return min(ts) - pub[k] if ts else None

        def quant(xs):
            xs = [x for x in xs if x is not None]
            return (round(float(np.median(xs)), 1), round(float(np.max(xs)), 1)) if xs else None

        def first_mask(k, provisional):  # arrival of k's first (non-)provisional mask
            kinds = got["mask_provisional"].get(k, [])
            times = got["mask"].get(k, [])
            return next((t for t, p in zip(times, kinds) if p == provisional), None)

        def lat(k, provisional):
            t = first_mask(k, provisional) if provisional is not None else \
                (got["mask"][k][0] if got["mask"].get(k) else None)
            return t - pub[k] if t is not None and k in pub else None

        def mask_iou(provisional, what="iou"):  # mean IoU (recall) of each keyframe's last
            vals = []  # (non-)provisional mask
            for k, kinds in got["mask_provisional"].items():
                ious = got.get(what, {}).get(k, [])
                sel = [x for x, p in zip(ious, kinds) if p == provisional]
                if sel:
                    vals.append(sel[-1])
            return (round(float(np.mean(vals)), 3), len(vals)) if vals else None

        def r1(x):
            return round(x, 1) if x is not None else None

        final_runs_t = seg.diag.timings.get("segment")
        t_ooi = next((t for t, st in ooi if st == sfm_last), None)
        segc = seg.diag.counters
        out.update({
            "ooi_clouds_received": len(ooi),
            "latency_last_keyframe_to_ooi_s": round(t_ooi - pub[sfm_last], 1)
            if t_ooi and sfm_last in pub else None,
            "ooi_cloud_of_last_keyframe": sfm_last == last_kf,
            "latency_last_keyframe_to_first_mask_s": r1(lat(last_kf, None)),
            "last_keyframe_first_mask_provisional": bool(
                got["mask_provisional"].get(last_kf, [False])[0]),
            "latency_last_keyframe_to_final_mask_s": r1(lat(last_kf, False)),
            "masks_of_last_keyframe": len(got["mask"].get(last_kf, [])),
            "latency_last_keyframe_to_sfm_cloud_s": round(got["sfm"][sfm_last] - pub[sfm_last], 1)
            if sfm_last in got["sfm"] and sfm_last in pub else None,
            "latency_sfm_cloud_median_max_s": quant([sfm_latency(k) for k in kf_stamps]),
            "latency_cloud_median_max_s": quant([cloud_latency(k) for k in kf_stamps]),
            "latency_first_mask_median_max_s": quant([lat(k, None) for k in kf_stamps]),
            "latency_final_mask_median_max_s": quant([lat(k, False) for k in kf_stamps]),
            "full_runs": seg.runs, "last_full_run_s": round(final_runs_t or 0.0, 1),
            "cloud_only_runs": seg.cloud_runs,
            "cloud_only_run_s_median": round(seg.diag.timings.get("cloud_run_median", 0.0), 1),
            "masks_provisional_published": segc.get("masks_provisional_published", 0),
            "masks_provisional_refreshed": segc.get("masks_provisional_refreshed", 0),
            "iou_last_provisional_mask": mask_iou(True),
            "iou_final_mask": mask_iou(False),
            "recall_final_mask": mask_iou(False, "recall"),
            "masks_final_published": segc.get("masks_published", 0),
            "masks_final_reused": segc.get("masks_reused", 0),
            "keyframes_without_final_mask": sum(
                1 for k in seg.keyframes if not any(
                    not p for p in got["mask_provisional"].get(k, []))),
            "provisional_mask_s": round(seg.diag.timings.get("provisional_mask", 0.0), 2),
        })
        c = sfm.diag.counters
        sc = seg.diag.counters
        out.update({
            "received_by_sfm_node": c.get("images", 0),
            "dropped": {k: v for k, v in c.items() if k.startswith("dropped") and v},
            "pose_gaps": c.get("pose_gaps", 0), "pose_jumps": c.get("pose_jumps", 0),
            "pose_gap_last_s": sfm.diag.values.get(
                "pose_gap_last_s"),
            "skipped": {k: v for k, v in c.items() if k.startswith("skipped") and v},
            "keyframes": sfm.selector.accepted, "keyframes_processed": sfm.keyframes_processed,
            "sfm_points": int(sfm.diag.values.get("points", 0)),
            "sfm_map_mb": sfm.diag.values.get("sfm_map_mb"),
            "segmentation_runs": seg.runs,
            "ooi_points": len(msgconv.pointcloud2_to_xyzrgb(got["ooi"][-1][1])[0])
            if got["ooi"] else 0,
            "sfm_backlog_after_stream_s": round(t_done_sfm - (t0 + duration), 1),
            "images_decoded": c.get("images_decoded", 0),
            "sfm_downscale": sfm.sfm_factor,
            "keyframe_s_median": round(sfm.diag.timings.get("keyframe_median", 0.0), 2),
            "segment_s": round(seg.diag.timings.get("segment", 0.0), 1),
            "seg_keyframes_kept": len(seg.keyframes),
            "seg_evicted": sc.get("dropped_keyframe_budget", 0)
            + sc.get("dropped_old_keyframes", 0),
            "seg_keyframe_image_mb": seg.diag.values.get("keyframe_image_mb"),
            "seg_image_budget_mb": seg.diag.values.get("image_budget_mb"),
            "masks_received": len(got["mask"]),
        })
        sfm.close()
        seg.close()
    else:
        out["received_by_subscriber"] = got["images"]
    out["wall_s"] = round(time.monotonic() - t0, 1)
    out["process_cpu_s"] = round(time.process_time() - cpu0, 1)
    out["worker_processes_cpu_s"] = round(sum(kid_cpu.values()), 1)  # to the stream's end
    out["worker_processes_rss_mb_last_peak"] = ((round(rss_kids[-1]), round(max(rss_kids)))
                                                if rss_kids else None)
    out["loadavg_1min_start_end"] = (round(load0, 1), round(os.getloadavg()[0], 1))
    ex.shutdown(timeout_sec=5)
    for n in nodes:
        n.destroy_node()
    rclpy.shutdown(context=ctx)
    out["peak_rss_mb_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def time_sfm(capture, factors: list[int], n: int = 20) -> None:
    """Offline: SfM seconds per keyframe on the first n views downscaled by each factor, as
    the node's worker runs it (alone in the process, unlike inside the stream)."""
    import numpy as np

    from ooi_seg_ros.core.types import View
    from ooi_seg_ros.nodes.common import downscale_camera, downscale_rgb
    from ooi_seg_ros.sfm.incremental import IncrementalSfM

    for f in factors:
        sfm = IncrementalSfM()
        ts = []
        for v in capture.views[:n]:
            sv = View(v.key, v.stamp_ns, downscale_camera(v.camera, f), v.pose,
                      image=downscale_rgb(v.get_image(), f))
            t = time.monotonic()
            sfm.add_keyframe(sv)
            ts.append(time.monotonic() - t)
        print(f"SfM on 1/{f} ({sv.camera.width}x{sv.camera.height}): median "
              f"{np.median(ts):.2f} s per keyframe over {len(ts)}, {len(sfm.cloud())} points",
              flush=True)


def replay_runs(n_views: int, every: int, seg_params: tuple, all_too: bool = True) -> None:
    """Offline and deterministic: the segmentation node's full runs on the demo bag's first
    ``n_views`` keyframes, one run every ``every`` keyframes on the SfM cloud of that moment,
    called synchronously (no load, no timing noise), with incremental final masks and with
    every keyframe re-masked, side by side: masks made per run, the run's CPU seconds (this
    process and the worker process the node hands full runs to), and the mean IoU against the
    bag's ground truth of the final mask each keyframe holds after each run (what a consumer
    of ``ooi/mask`` has); then the runs' wall seconds. ``all_too`` False: the incremental
    runs only (the other column is left empty)."""
    import uuid
    from pathlib import Path

    from ooi_seg_ros.bag import BagReader
    from ooi_seg_ros.core.types import View
    from ooi_seg_ros.sfm.incremental import IncrementalSfM

    bag = BagReader(str(Path(__file__).resolve().parents[1] / "bags" / "demo.mcap"))
    names = {"/camera/camera_info": 0, "/camera/pose": 1, "/camera/image_raw": 2,
             "/ground_truth/mask": 3}
    msgs = [[], [], [], []]
    for topic, ty, _t, data in bag.messages(topics=list(names)):
        msgs[names[topic]].append(bag.decode(ty, data))
    kfs = list(zip(*[m[:n_views] for m in msgs]))
    gt = {msgconv.stamp_to_ns(g.header.stamp): msgconv.image_to_mask(g) for *_x, g in kfs}
    sfm = IncrementalSfM()
    clouds = {}
    for k, (info, pose, img, _g) in enumerate(kfs):
        st = msgconv.stamp_to_ns(img.header.stamp)
        sfm.add_keyframe(View("", st, msgconv.camera_info_to_intrinsics(info),
                              msgconv.pose_from_msg(pose.pose), image=msgconv.image_to_rgb(img)))
        if (k + 1) % every == 0 or k + 1 == len(kfs):
            c = sfm.cloud()
            stamp = msgconv.ns_to_stamp(st)
            clouds[k + 1] = (msgconv.sfm_cloud_to_pointcloud2(c, stamp),
                             msgconv.observations_to_pointcloud2(c, stamp))
    rows = {}
    # a warm-up run first: the first segment() call of a process makes slightly different
    # masks than the later ones (some one-time state in the segmentation core), which would
    # favour whichever mode runs second
    for incremental in ("warm-up", True, False) if all_too else ("warm-up", True):
        ctx = Context()
        rclpy.init(context=ctx)
        node = SegmentationNode(context=ctx, namespace="/replay_" + uuid.uuid4().hex[:8],
                                parameter_overrides=[
                                    Parameter("every_n_keyframes", value=0),
                                    Parameter("provisional_masks", value=False),
                                    Parameter("cloud_runs", value=False),
                                    Parameter("incremental_final", value=bool(incremental))]
                                + list(seg_params))
        held: dict = {}
        node.pub_mask.publish = lambda m, held=held: held.__setitem__(
            msgconv.stamp_to_ns(m.header.stamp), msgconv.image_to_mask(m))
        out = []
        try:
            fed = 0
            for n, (points, obs) in sorted(clouds.items()):
                for info, pose, img, _g in kfs[fed:n]:
                    node.on_kf_info(info)
                    node.on_kf_pose(pose)
                    node.on_kf_image(img)
                fed = n
                node.on_points(points)
                node.on_obs(obs)
                assert node._busy.acquire(blocking=False)
                c0, w0 = _cpu_with_children(), time.perf_counter()
                node._run()
                cpu, wall = _cpu_with_children() - c0, time.perf_counter() - w0
                if node.last_error:
                    raise RuntimeError(node.last_error)
                made = node.diag.values.get("masks_refined_last_run", n)
                iou = np.mean([float((held[s] & gt[s]).sum() / max((held[s] | gt[s]).sum(), 1))
                               for s in held])
                out.append((n, int(made), round(cpu, 1), round(float(iou), 3), wall))
                if incremental == "warm-up":
                    break
        finally:
            node.destroy_node()
            rclpy.shutdown(context=ctx)
        rows[incremental] = out
    print("\n| keyframes at the run | incremental: masks made / run CPU s (process and "
          "worker processes) / mean final IoU | every keyframe: masks made / run CPU s / mean "
          "final IoU |")
    print("|---|---|---|")
    if not all_too:  # an empty column
        rows[False] = [(r[0], 0, 0.0, float("nan"), 0.0) for r in rows[True]]
    for a, b in zip(rows[True], rows[False]):
        print(f"| {a[0]} | {a[1]} / {a[2]} / {a[3]:.3f} | {b[1]} / {b[2]} / {b[3]:.3f} |")
    ta, tb = sum(r[2] for r in rows[True]), sum(r[2] for r in rows[False])
    print(f"| all runs | {sum(r[1] for r in rows[True])} / {ta:.1f} / "
          f"{rows[True][-1][3]:.3f} | {sum(r[1] for r in rows[False])} / {tb:.1f} / "
          f"{rows[False][-1][3]:.3f} |")
    print(f"run wall s, all runs: incremental {sum(r[4] for r in rows[True]):.1f}, every "
          f"keyframe {sum(r[4] for r in rows[False]):.1f}")


def _cpu_with_children() -> float:
    """CPU seconds of this process and its live child processes (the segmentation node's
    full runs go to a worker process, whose time ``time.process_time`` does not see)."""
    proc = psutil.Process()
    total = sum(proc.cpu_times()[:2])
    for kid in proc.children(recursive=True):
        try:
            total += sum(kid.cpu_times()[:2])
        except psutil.Error:
            pass
    return total


def compare_seg_downscale(capture, factor: int) -> None:
    """Offline: the segmentation on full-size views vs on 1/factor copies (as the node keeps
    them), one SfM cloud, masks upscaled to full size; IoU against the ground truth."""
    import dataclasses

    import numpy as np

    from ooi_seg_ros.core.types import Capture, View
    from ooi_seg_ros.nodes.common import (decode_guide, downscale_camera, downscale_rgb,
                                          encode_guide, upscale_mask)
    from ooi_seg_ros.seg.pipeline import make_config, segment
    from ooi_seg_ros.sfm.incremental import IncrementalSfM

    small = [View(v.key, v.stamp_ns, downscale_camera(v.camera, factor), v.pose,
                  image=downscale_rgb(v.get_image(), factor)) for v in capture.views]
    sfm = IncrementalSfM()
    for v in small:
        sfm.add_keyframe(v)
    cloud = sfm.cloud()
    cam = capture.views[0].camera
    for f in (1, factor):
        views = small if f == factor else [View(v.key, v.stamp_ns, v.camera, v.pose,
                                                image=v.get_image()) for v in capture.views]
        s = factor / f  # cloud observations are in the 1/factor pixels
        c = dataclasses.replace(cloud, views=views, error=cloud.error * s,
                                obs_xy=((cloud.obs_xy + 0.5) * s - 0.5).astype(np.float32))
        t = time.monotonic()
        r = segment(Capture(views=views), c, make_config("ours"))
        dt = time.monotonic() - t
        ious, guided = [], []
        for v in capture.views:
            m = upscale_mask(r.masks[v.key], f, cam.width, cam.height)
            ious.append((m & v.gt_mask).sum() / max((m | v.gt_mask).sum(), 1))
            if f > 1:  # as the node places a final mask's outline: by a JPEG of the image
                g = decode_guide(encode_guide(v.get_image(), 90))
                m = upscale_mask(r.masks[v.key], f, cam.width, cam.height, guide=g)
                guided.append((m & v.gt_mask).sum() / max((m | v.gt_mask).sum(), 1))
        if guided:
            print(f"  masks enlarged with the image's JPEG q90 as guide (the node's final "
                  f"masks): mean IoU {np.mean(guided):.3f} (min {np.min(guided):.3f})")
        print(f"segmentation on {views[0].camera.width}x{views[0].camera.height} keyframes: "
              f"{dt:.1f} s, mean IoU {np.mean(ious):.3f} (min {np.min(ious):.3f}) over "
              f"{len(ious)} views, SfM cloud {len(cloud)} points", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="aircraft")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--unique", type=int, default=60, help="views rendered along the orbit")
    ap.add_argument("--baseline-duration", type=float, default=20.0)
    ap.add_argument("--compare-seg-downscale", type=int, default=0, metavar="F",
                    help="only compare the segmentation on full-size vs 1/F keyframes, offline")
    ap.add_argument("--time-sfm", default="", metavar="F1,F2",
                    help="only time SfM per keyframe at these downscale factors, offline")
    ap.add_argument("--default-malloc", action="store_true",
                    help="leave glibc's heap settings alone (the nodes' main() limits them)")
    ap.add_argument("--cache", default="",
                    help="pickle file for the rendered views (rendered and written if missing)")
    ap.add_argument("--budget-mb", type=float, default=0.0,
                    help="segmentation node image_budget_mb (0 = its default)")
    ap.add_argument("--no-fast-path", action="store_true",
                    help="segmentation node without provisional masks and cloud-only runs "
                         "(OOI cloud and masks only from full runs), for comparison")
    ap.add_argument("--replay-demo", type=int, default=0, metavar="EVERY",
                    help="only replay the node's full runs offline on the demo bag, one every "
                         "EVERY keyframes, incremental vs all masks (deterministic)")
    ap.add_argument("--replay-incremental-only", action="store_true",
                    help="with --replay-demo: skip the every-keyframe runs")
    ap.add_argument("--all-masks", action="store_true",
                    help="every full run re-masks every keyframe (incremental_final false); "
                         "with --seg-param every_n_keyframes=10 the behaviour before "
                         "incremental final runs, for comparison")
    ap.add_argument("--seg-param", action="append", default=[], metavar="NAME=VALUE",
                    help="extra segmentation_node parameter (YAML value; after --no-fast-path)")
    args = ap.parse_args()
    seg_params = tuple(Parameter(k, value=yaml.safe_load(v))
                       for k, v in (a.split("=", 1) for a in args.seg_param))
    if args.all_masks:
        seg_params = (Parameter("incremental_final", value=False),) + seg_params
    if args.replay_demo:
        replay_runs(args.unique, args.replay_demo, seg_params, not args.replay_incremental_only)
        return
    if not args.default_malloc:
        limit_heap_growth()  # as the nodes' main() does (run_node)
    w, h = (int(x) for x in args.size.split("x"))
    t = time.monotonic()
    key = (args.scene, args.unique, w, h)
    cap = None
    if args.cache and os.path.exists(args.cache):
        with open(args.cache, "rb") as fh:
            cached = pickle.load(fh)
        cap = cached["capture"] if cached.get("key") == key else None
    if cap is None:
        cap = simulate_capture(args.scene, n_views=args.unique, width=w, height=h, seed=0,
                               supersample=1).capture
        for v in cap.views:
            v.get_image()
        if args.cache:
            with open(args.cache, "wb") as fh:
                pickle.dump({"key": key, "capture": cap}, fh)
    print(f"rendered {args.unique} views {w}x{h} in {time.monotonic() - t:.0f} s", flush=True)
    if args.time_sfm:
        time_sfm(cap, [int(x) for x in args.time_sfm.split(",")])
        return
    if args.compare_seg_downscale:
        compare_seg_downscale(cap, args.compare_seg_downscale)
        return
    base = run_case(cap, args.fps, args.baseline_duration, with_nodes=False)
    print(f"baseline (bare subscriber, {args.baseline_duration:.0f} s): {base}", flush=True)
    res = run_case(cap, args.fps, args.duration, with_nodes=True, budget_mb=args.budget_mb,
                   fast_path=not args.no_fast_path, seg_params=seg_params)
    print(f"nodes (sfm_node + segmentation_node, {args.duration:.0f} s): {res}", flush=True)
    print("\n| case | s | published | received | decoded | dropped | keyframes (processed) | "
          "SfM s/keyframe | last kf -> SfM cloud / OOI cloud / first mask / final mask s | same, "
          "median (max) over keyframes | RSS MB first/mid/last |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| bare subscriber | {args.baseline_duration:.0f} | {base['published']} | "
          f"{base['received_by_subscriber']} | - | - | - | - | - | - | "
          f"{base['rss_mb_first']:.0f} / {base['rss_mb_mid']:.0f} / {base['rss_mb_last']:.0f} |")

    def mm(x):
        return f"{x[0]} ({x[1]})" if x else "-"

    print(f"| sfm + segmentation nodes | {args.duration:.0f} | {res['published']} | "
          f"{res['received_by_sfm_node']} | {res['images_decoded']} | {res['dropped']} | "
          f"{res['keyframes']} ({res['keyframes_processed']}) | {res['keyframe_s_median']} "
          f"(1/{res['sfm_downscale']}) | {res['latency_last_keyframe_to_sfm_cloud_s']} / "
          f"{res['latency_last_keyframe_to_ooi_s']} / "
          f"{res['latency_last_keyframe_to_first_mask_s']} / "
          f"{res['latency_last_keyframe_to_final_mask_s']} | "
          f"{mm(res['latency_sfm_cloud_median_max_s'])} / "
          f"{mm(res['latency_cloud_median_max_s'])} / "
          f"{mm(res['latency_first_mask_median_max_s'])} / "
          f"{mm(res['latency_final_mask_median_max_s'])} | {res['rss_mb_first']:.0f} / "
          f"{res['rss_mb_mid']:.0f} / {res['rss_mb_last']:.0f} |")
    print(f"\nfull runs {res['full_runs']} (last {res['last_full_run_s']} s), final masks "
          f"published {res['masks_final_published']}, kept from earlier runs "
          f"{res['masks_final_reused']}, keyframes without a final mask "
          f"{res['keyframes_without_final_mask']}; mask IoU last provisional "
          f"{res['iou_last_provisional_mask']} / final {res['iou_final_mask']} (mean, count), "
          f"final recall {res['recall_final_mask']}; "
          f"wall {res['wall_s']} s, process CPU {res['process_cpu_s']} s (worker processes "
          f"{res.get('worker_processes_cpu_s')} CPU-s, RSS last/peak "
          f"{res.get('worker_processes_rss_mb_last_peak')} MB), load average "
          f"{res['loadavg_1min_start_end']} (start, end)")


if __name__ == "__main__":
    main()
