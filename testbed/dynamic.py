"""The harness side of a changing world and faulty sensors, for ``dopeslam run``:

- the message stream through the scenario's (or the command line's) sensor faults (``sim.faults``);
- an object store carried over from an earlier run (``--store PATH``): loaded before the first
  message, saved after the last (rows a person edited in that file stay as they are);
- what the report says about it: ``labels_summary.stale_labels`` (labels left where an object no
  longer stands), per moved or added object the delay until it was labelled at its new place, what
  the people walking through did to the detections and the LiDAR, the faults' counts, and per store
  row what the run did to it (kept, updated, retired, added).

Scoring is against the final world (``Episode.objects`` after the last event); earlier states are
what makes a label stale.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from stack.object_store import ObjectStore
from stack.retire import RETIRED, RetireConfig
from stack.transforms import transform_points
from testbed.scoring import FALSE_LABEL_M

MOVED_M = 0.05  # a stored row whose label moved further than this was updated
PEOPLE_IN_VIEW = 0.02  # an image with more than this share covered by people counts as "with people"


class DynamicRun:
    """Wires faults, the carried-over store and retirement into one episode's pipeline."""

    def __init__(self, ep, pipe, faults=(), store_path=None, retire: RetireConfig | None = RetireConfig()):
        """``faults``: ``NAME=VALUE`` items over the scenario's ``[faults]`` (``sim.faults``)."""
        from sim.faults import FaultInjector, parse_overrides

        self.ep, self.pipe = ep, pipe
        self.faults = parse_overrides(faults or (), ep.sc.faults)
        self.injector = FaultInjector(self.faults, ep.seed) if self.faults.active else None
        if retire is not None and getattr(pipe, "retirement", None) is None:
            from stack.retire import Retirement

            pipe.retirement = Retirement(retire)
        self.store_path = None if store_path is None else Path(store_path)
        self.before: dict[int, dict] = {}
        if self.store_path is not None and self.store_path.exists():
            s = pipe.store
            pipe.store = ObjectStore.load(self.store_path, dims=s.dims, gate_m=s.gate_m, policy=s.policy,
                                          evidence=s.evidence)
            self.before = {o.id: {"class": o.cls, "xyz": o.xyz.copy(), "status": o.status, "edited": o.edited}
                           for o in pipe.store}
        self.people = {"images": 0, "images_with_people": 0, "predictions_with_people": 0,
                       "false_positives_with_people": 0, "predictions_without_people": 0,
                       "false_positives_without_people": 0, "objects_in_view_with_people": 0,
                       "objects_hidden_by_people": 0}

    def messages(self):
        """The episode's messages as the (faulty) drivers publish them."""
        frames = self.ep.frames()
        return frames if self.injector is None else self.injector.apply(frames)

    def on_image(self, frame, detections, flags, truths) -> None:
        """Per detected image: detections with and without people in view; objects they hide."""
        if not (self.ep.events and self.ep.events.walkers):
            return
        share = self.ep.occluder_fraction(frame)
        self.people["images"] += 1
        key = "with_people" if share > PEOPLE_IN_VIEW else "without_people"
        if share > PEOPLE_IN_VIEW:
            self.people["images_with_people"] += 1
            for t in truths:
                if t["in_front"] and t["distance_m"] < 2.5 and _in_image(t["keypoints_px"][8], frame.info):
                    self.people["objects_in_view_with_people"] += 1
                    self.people["objects_hidden_by_people"] += int(t["visible_fraction"] < 0.5)
        for det, ok in zip(detections, flags):
            if det.fpr_pass:
                self.people[f"predictions_{key}"] += 1
                self.people[f"false_positives_{key}"] += int(not ok)

    # --- the report ---
    def report(self, report: dict, store, T_world_map: np.ndarray) -> None:
        s = report["labels_summary"]
        stale = stale_labels(s["map_labels"], self.ep.past_positions())
        s["stale_labels"] = len(stale)
        s["stale_label_rows"] = stale
        report["events"] = self.ep.event_log
        if self.ep.event_log:
            report["moved_objects"] = self._relabel_delays(report["labels"], store)
        if getattr(self.pipe, "retirement", None) is not None:
            report["retirement"] = self.pipe.retirement.summary()
        if self.ep.events and self.ep.events.walkers:
            pts = self.ep.lidar_points
            report["occluders"] = {**self.people, "walkers": len(self.ep.events.walkers),
                                   "lidar_points_on_people": self.ep.lidar_person_points,
                                   "lidar_share_on_people": self.ep.lidar_person_points / pts if pts else None,
                                   "odometry_ate_rmse_m": report["odometry"]["ate_rmse_m"]}
        if self.injector is not None:
            report["faults"] = {"settings": self.faults.active, "counts": dict(self.injector.counts)}
        if self.store_path is not None:
            report["store"] = self._store_changes(store, T_world_map)

    def _relabel_delays(self, label_rows: list[dict], store) -> list[dict]:
        """Per object moved or added during the run: when, and how long until its label at the new
        place was published (None: it was not)."""
        from stack.evidence import EvidenceConfig, assess

        by_id = {o.id: o for o in store}
        out = []
        for e in self.ep.event_log:
            if e["kind"] not in ("move", "add"):
                continue
            row = next((r for r in label_rows if r["object"] == e["object"]), None)
            entry = {"object": e["object"], "kind": e["kind"], "t": e["t"], "to_xyz": e.get("to_xyz"),
                     "labelled": bool(row and row["id"] is not None and not row["false_label"]),
                     "error_m": None if row is None else row["error_m"], "relabel_delay_s": None}
            obj = by_id.get(row["id"]) if entry["labelled"] else None
            if obj is not None:
                hist = [h for h in obj.history if h.stamp >= e["t"]]
                config = store.evidence or EvidenceConfig()
                for k in range(1, len(hist) + 1):
                    trial = copy.copy(obj)
                    trial.history = hist[:k]
                    if assess([trial], config, store.floor)[obj.id][0] == "label":
                        entry["relabel_delay_s"] = hist[k - 1].stamp - e["t"]
                        break
            out.append(entry)
        return out

    def _store_changes(self, store, T_world_map) -> dict:
        rows = []
        for o in store:
            b = self.before.get(o.id)
            if b is None:
                change = "added"
            elif o.edited:
                change = "kept (edited)"
            elif o.status == RETIRED and b["status"] != RETIRED:
                change = "retired"
            elif float(np.linalg.norm(o.xyz - b["xyz"])) > MOVED_M:
                change = "updated"
            else:
                change = "unchanged"
            rows.append({"id": o.id, "class": o.cls, "status": o.status, "change": change,
                         "xyz": [float(v) for v in transform_points(T_world_map, o.xyz[None])[0]]})
        counts = {}
        for r in rows:
            counts[r["change"]] = counts.get(r["change"], 0) + 1
        return {"path": str(self.store_path), "rows_before": len(self.before), "rows_after": len(rows),
                "changes": counts, "rows": rows}

    def save_store(self, store) -> None:
        """Save the updated store where it came from (edited rows in that file are kept as they are)."""
        if self.store_path is not None:
            self.store_path.parent.mkdir(parents=True, exist_ok=True)
            store.save(self.store_path)


def stale_labels(map_rows: list[dict], past_positions, threshold_m: float = FALSE_LABEL_M) -> list[dict]:
    """Published labels that are not correct and lie within ``threshold_m`` of a place where an object
    of their class stood earlier in the run and stands no longer."""
    out = []
    for r in map_rows:
        if r["verdict"] == "correct":
            continue
        p = np.asarray(r["label_xyz"], dtype=float)
        for name, cls, xyz in past_positions:
            d = float(np.linalg.norm(p - xyz))
            if cls == r["class"] and d <= threshold_m:
                out.append({"id": r["id"], "class": r["class"], "was": name, "distance_m": d})
                break
    return out


def _in_image(uv, info) -> bool:
    return bool(np.all(np.isfinite(uv)) and 0 <= uv[0] < info.width and 0 <= uv[1] < info.height)



