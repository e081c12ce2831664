"""Hand-built OpenPCDet / mmdetection3d infos structures and matching result rows (export tests, benchmark).

The structures follow what the projects' converters write (facts from OpenPCDet
``pcdet/datasets/kitti/kitti_dataset.py::get_infos``, ``pcdet/datasets/waymo/waymo_utils.py`` and
mmdetection3d ``tools/dataset_converters/update_infos_to_v2.py``), documented in docs/training.md:

- OpenPCDet KITTI: a list of frame dicts with ``point_cloud`` {num_features, lidar_idx}, ``image``,
  ``calib`` and ``annos`` whose arrays have one row per label line, DontCare included, in file
  order (``dimensions`` are l, h, w; ``index`` is the non-DontCare ordinal, −1 for DontCare;
  ``gt_boxes_lidar`` has the non-DontCare rows only).
- OpenPCDet Waymo: ``point_cloud`` {num_features, lidar_sequence, sample_idx}, ``frame_id``,
  ``metadata`` {context_name, timestamp_micros}, ``annos`` with ``obj_ids`` and l, w, h dimensions.
- OpenPCDet gt-database infos (``create_groundtruth_database``): {class: [entry, …]}; a KITTI entry
  names its frame by ``image_idx`` and its object by ``gt_idx`` = i over ``gt_boxes_lidar`` (the
  non-DontCare ordinal); a Waymo entry by ``sequence_name``, ``sample_idx`` and ``gt_idx`` = the annos row.
- mmdet3d v2: {"metainfo": {categories, dataset, info_version}, "data_list": [{sample_idx,
  lidar_points: {lidar_path}, instances: [{bbox_3d (camera x, y, z, l, h, w, ry), bbox_label_3d, index, …}]}]}.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from results_factory import make_row

# one label line: class, l, w, h
Obj = tuple[str, float, float, float]
KITTI_CLASSES = ("Pedestrian", "Cyclist", "Car", "Van", "Truck", "Person_sitting", "Tram", "Misc")


def kitti_frames_and_rows(
    frames: dict[str, Sequence[Obj]], audited: Sequence[str] = ("Car", "Van", "Truck"), model: str = "bev"
) -> tuple[dict[str, Sequence[Obj]], list[dict[str, Any]]]:
    """Result rows (one per audited object, object_index = non-DontCare ordinal) with a unique covariance each."""
    rows = []
    k = 0
    p = 6 if model == "bev" else 8
    for fid, objs in frames.items():
        ordinal = -1
        for line, (name, l, w, h) in enumerate(objs, start=1):
            if name == "DontCare":
                continue
            ordinal += 1
            if name not in audited:
                continue
            k += 1
            cov = np.diag(np.linspace(1.0, 2.0, p) * 1e-3 * k)
            rows.append(
                make_row(
                    fid, ordinal, class_name=name, length=l, width=w, height=h, label_line=line,
                    cov=cov.ravel().tolist(), cov_dim=p, model=model, hull_iou=min(0.9, 0.05 * k), num_points=10 * k,
                )
            )  # fmt: skip
    return frames, rows


def openpcdet_kitti_infos(frames: dict[str, Sequence[Obj]]) -> list[dict[str, Any]]:
    infos = []
    for fid, objs in frames.items():
        names = np.array([o[0] for o in objs])
        dc = names == "DontCare"
        dims = np.array(
            [[o[1], o[3], o[2]] if not d else [-1.0, -1.0, -1.0] for o, d in zip(objs, dc)], dtype=float
        ).reshape(-1, 3)
        n_obj = int((~dc).sum())
        annos = {
            "name": names,
            "truncated": np.zeros(len(objs)),
            "occluded": np.zeros(len(objs)),
            "alpha": np.zeros(len(objs)),
            "bbox": np.tile([100.0, 100.0, 200.0, 200.0], (len(objs), 1)).astype(np.float32),
            "dimensions": dims,
            "location": np.where(dc[:, None], -1000.0, np.tile([1.0, 1.5, 10.0], (len(objs), 1))),
            "rotation_y": np.where(dc, -10.0, 0.1),
            "score": -np.ones(len(objs)),
            "difficulty": np.zeros(len(objs), np.int32),
            "index": np.array(list(range(n_obj)) + [-1] * (len(objs) - n_obj), dtype=np.int32),
            # l, w, h of the non-DontCare rows (position and heading do not enter the export)
            "gt_boxes_lidar": np.array(
                [[0.0, 0.0, 0.0, o[1], o[2], o[3], 0.0] for o, d in zip(objs, dc) if not d]
            ).reshape(-1, 7),
            "num_points_in_gt": -np.ones(len(objs), dtype=np.int32),
        }
        infos.append(
            {
                "point_cloud": {"num_features": 4, "lidar_idx": fid},
                "image": {"image_idx": fid, "image_shape": np.array([375, 1242], dtype=np.int32)},
                "calib": {"P2": np.eye(4), "R0_rect": np.eye(4), "Tr_velo_to_cam": np.eye(4)},
                "annos": annos,
            }
        )
    return infos


def mmdet3d_kitti_infos(frames: dict[str, Sequence[Obj]]) -> dict[str, Any]:
    data_list = []
    cats = {c: i for i, c in enumerate(KITTI_CLASSES)}
    for fid, objs in frames.items():
        instances = []
        ordinal = -1
        for name, l, w, h in objs:
            dc = name == "DontCare"
            if not dc:
                ordinal += 1
            instances.append(
                {
                    "bbox": [100.0, 100.0, 200.0, 200.0],
                    "bbox_label": -1 if dc else cats[name],
                    "bbox_3d": [1.0, 1.5, 10.0, -1.0, -1.0, -1.0, -10.0] if dc else [1.0, 1.5, 10.0, l, h, w, 0.1],
                    "bbox_label_3d": -1 if dc else cats[name],
                    "index": -1 if dc else ordinal,
                    "truncated": 0.0,
                    "occluded": 0,
                    "difficulty": 0,
                }
            )
        data_list.append(
            {
                "sample_idx": int(fid),
                "lidar_points": {"num_pts_feats": 4, "lidar_path": f"{fid}.bin"},
                "instances": instances,
            }
        )
    return {
        "metainfo": {"categories": {**cats, "DontCare": -1}, "dataset": "kitti", "info_version": "1.1"},
        "data_list": data_list,
    }


def openpcdet_waymo_infos(frames: dict[str, Sequence[tuple[str, str, float, float, float]]]) -> list[dict[str, Any]]:
    """frames: '<segment>:<timestamp>' → [(obj_id, class, l, w, h), …]."""
    infos = []
    for cnt, (fid, objs) in enumerate(frames.items()):
        segment, ts = fid.split(":")
        infos.append(
            {
                "point_cloud": {
                    "num_features": 5,
                    "lidar_sequence": f"segment-{segment}_with_camera_labels",
                    "sample_idx": cnt,
                },
                "frame_id": f"segment-{segment}_with_camera_labels_{cnt:03d}",
                "metadata": {"context_name": segment, "timestamp_micros": int(ts)},
                "pose": np.eye(4, dtype=np.float32),
                "annos": {
                    "name": np.array([o[1] for o in objs]),
                    "difficulty": np.zeros(len(objs), np.int64),
                    "dimensions": np.array([[o[2], o[3], o[4]] for o in objs], dtype=float).reshape(-1, 3),
                    "location": np.zeros((len(objs), 3)),
                    "heading_angles": np.zeros(len(objs)),
                    "obj_ids": np.array([o[0] for o in objs]),
                    "num_points_in_gt": np.full(len(objs), 50),
                    "gt_boxes_lidar": np.array(
                        [[0.0, 0.0, 0.0, o[2], o[3], o[4], 0.0, 0.0, 0.0] for o in objs]
                    ).reshape(-1, 9),
                },
            }
        )
    return infos


def openpcdet_kitti_infos_from_labels(root: Path) -> list[dict[str, Any]]:
    """OpenPCDet KITTI infos of every labelled frame of a KITTI root, as ``get_infos`` builds them from label_2 and calib."""
    from labelaudit.datasets.kitti import boxes_camera_to_lidar, read_calib, read_label

    frames = {}
    infos = []
    for p in sorted((root / "training" / "label_2").glob("*.txt")):
        lab = read_label(p)
        frames[p.stem] = [(n, l, w, h) for n, (h, w, l) in zip(lab.class_names, lab.dims_hwl)]
        info = openpcdet_kitti_infos({p.stem: frames[p.stem]})[0]
        annos = info["annos"]
        dc = np.array([n == "DontCare" for n in lab.class_names], dtype=bool)
        annos["location"] = lab.location.copy()
        annos["dimensions"] = lab.dims_hwl[:, [2, 0, 1]].copy()  # l, h, w
        annos["rotation_y"] = lab.rotation_y.copy()
        annos["bbox"] = lab.bbox2d.astype(np.float32)
        calib = read_calib(root / "training" / "calib" / f"{p.stem}.txt")
        annos["gt_boxes_lidar"] = boxes_camera_to_lidar(
            lab.location[~dc], lab.dims_hwl[~dc], lab.rotation_y[~dc], calib
        )
        infos.append(info)
    return infos


def openpcdet_dbinfos(infos: Sequence[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Gt-database infos of OpenPCDet infos (KITTI or Waymo), entry by entry as ``create_groundtruth_database`` writes them."""
    db: dict[str, list[dict[str, Any]]] = {}
    for info in infos:
        annos = info["annos"]
        gt_boxes = annos["gt_boxes_lidar"]
        pc_info = info["point_cloud"]
        # KITTI's gt_boxes_lidar rows are the non-DontCare objects (DontCare come last in KITTI's files)
        names = [str(n) for n in annos["name"] if n != "DontCare"]
        difficulty = [d for n, d in zip(annos["name"], annos["difficulty"]) if n != "DontCare"]
        for i in range(gt_boxes.shape[0]):
            name = names[i]
            if "lidar_sequence" in pc_info:
                where = {"sequence_name": pc_info["lidar_sequence"], "sample_idx": pc_info["sample_idx"]}
                path = f"gt_database/{pc_info['lidar_sequence']}_{pc_info['sample_idx']:04d}_{name}_{i}.bin"
            else:
                where = {"image_idx": pc_info["lidar_idx"]}
                path = f"gt_database/{pc_info['lidar_idx']}_{name}_{i}.bin"
            entry = {"name": name, "path": path, **where, "gt_idx": i, "box3d_lidar": gt_boxes[i], "num_points_in_gt": 20,
                     "difficulty": difficulty[i]}  # fmt: skip
            db.setdefault(name, []).append(entry)
    return db
