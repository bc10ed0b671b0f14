"""The persistent object store: association, labelling policies, .xlsx/.json files, hand edits."""
import json
import math
import zipfile

import numpy as np
import openpyxl
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from stack.object_store import (COLUMNS, POLICIES, MapObject, ObjectStore, ObjectStoreError, Observation,
                                _write_xlsx, label_of, read_objects)

DIMS = {"Mustard": (0.160050, 0.048574, 0.065133), "Cookies": (0.167243, 0.040152, 0.122746),
        "E": (0.100, 0.140, 0.035)}


def obs(t, xyz, cls="Mustard", belief=10.0, fpr=True, range_m=1.0, yaw=0.0):
    quat = Rotation.from_euler("z", yaw).as_quat()
    return Observation(float(t), cls, np.asarray(xyz, dtype=float), quat, belief, fpr, range_m)


# --- Association ----------------------------------------------------------------------------------

def test_a_detection_near_a_known_object_of_its_class_updates_it():
    store = ObjectStore(DIMS, gate_m=0.5, policy="last")
    a = store.add(obs(1.0, (1.0, 0.0, 0.5)))
    b = store.add(obs(2.0, (1.3, 0.1, 0.5)))
    assert a is b and len(store) == 1
    assert (a.id, a.observations, a.first_seen, a.last_seen) == (1, 2, 1.0, 2.0)
    np.testing.assert_allclose(a.xyz, (1.3, 0.1, 0.5))
    np.testing.assert_allclose(a.size, DIMS["Mustard"])


def test_a_detection_beyond_the_gate_or_of_another_class_is_a_new_object():
    store = ObjectStore(DIMS, gate_m=0.5)
    store.add(obs(1.0, (0.0, 0.0, 0.0)))
    far = store.add(obs(2.0, (0.6, 0.0, 0.0)))
    other_class = store.add(obs(3.0, (0.0, 0.0, 0.0), cls="Cookies"))
    assert [o.id for o in store] == [1, 2, 3]
    assert (far.id, other_class.id, other_class.cls) == (2, 3, "Cookies")


def test_the_nearest_object_within_the_gate_takes_the_detection():
    store = ObjectStore(DIMS, gate_m=1.0, policy="last")
    store.add(obs(0.0, (0.0, 0.0, 0.0)))
    store.add(obs(0.0, (1.5, 0.0, 0.0)))
    assert store.add(obs(1.0, (0.9, 0.0, 0.0))).id == 2


def test_an_infinite_gate_keeps_one_object_per_class_as_in_the_paper():
    store = ObjectStore(DIMS, gate_m=math.inf, policy="last")
    for t, x in enumerate([0.0, 3.0, -7.0]):
        store.add(obs(t, (x, 0.0, 0.0)))
    (only,) = store
    assert only.observations == 3 and only.xyz[0] == -7.0


def test_an_fpr_rejected_detection_starts_no_object_but_counts_on_a_known_one():
    store = ObjectStore(DIMS, policy="last-fpr")
    assert store.add(obs(0.0, (0.0, 0.0, 0.0), fpr=False)) is None and len(store) == 0
    store.add(obs(1.0, (0.0, 0.0, 0.0)))
    obj = store.add(obs(2.0, (0.2, 0.0, 0.0), fpr=False))
    assert obj.observations == 2 and obj.last_seen == 2.0
    np.testing.assert_allclose(obj.xyz, (0.0, 0.0, 0.0))  # the label ignores the rejected one


def test_an_object_edited_by_hand_is_not_moved_by_new_detections():
    store = ObjectStore(DIMS, policy="last")
    obj = store.add(obs(0.0, (0.0, 0.0, 0.0)))
    obj.xyz, obj.edited = np.array([0.05, 0.0, 0.0]), True
    store.add(obs(1.0, (0.3, 0.0, 0.0)))
    np.testing.assert_allclose(obj.xyz, (0.05, 0.0, 0.0))
    assert obj.observations == 2


def test_a_class_without_a_cuboid_size_is_refused():
    from stack.errors import ComponentError

    with pytest.raises(ComponentError, match="class 'Banana' at t=0.000 s: no cuboid size for that class"):
        ObjectStore(DIMS).add(obs(0.0, (0, 0, 0), cls="Banana"))


# --- Labelling policies (offline: a list of observations -> a label) ---------------------------------

HISTORY = [
    obs(1.0, (1.0, 0.0, 0.0), belief=5.0, range_m=0.7),
    obs(2.0, (2.0, 0.0, 0.0), belief=2.0, range_m=1.5),
    obs(3.0, (3.0, 0.0, 0.0), belief=8.0, range_m=2.0),
    obs(4.0, (4.0, 0.0, 0.0), belief=90.0, range_m=0.3, fpr=False),
]


@pytest.mark.parametrize("policy, x", [
    ("last", 4.0),         # the paper's: the last detection even though FPR rejected it
    ("last-fpr", 3.0),     # the last one FPR let through
    ("best-score", 2.0),   # the lowest belief sum among those FPR let through
    ("closest-fpr", 1.0),  # the one seen from nearest among those FPR let through
])
def test_single_detection_policies_pick_their_detection(policy, x):
    label = label_of(HISTORY, policy)
    assert label.xyz[0] == x
    assert label.score == next(o.belief_sum for o in HISTORY if o.xyz[0] == x)


def test_robust_mean_averages_the_fpr_passing_detections_and_drops_outliers():
    rng = np.random.default_rng(0)
    truth = np.array([1.0, 2.0, 0.5])
    inliers = [obs(t, truth + rng.normal(0, 0.01, 3), belief=4.0 + t, yaw=0.1 * (t - 2)) for t in range(5)]
    history = inliers + [obs(5, truth + (1.0, 0, 0), belief=3.0), obs(6, truth - (0, 2.0, 0), fpr=False)]
    label = label_of(history, "robust-mean")
    np.testing.assert_allclose(label.xyz, np.mean([o.xyz for o in inliers], axis=0), atol=1e-12)
    assert label.score == pytest.approx(6.0)
    assert Rotation.from_quat(label.quat_xyzw).as_euler("xyz")[2] == pytest.approx(0.0, abs=1e-9)


def test_no_label_without_an_fpr_passing_detection_except_for_the_paper_policy():
    rejected = [obs(0.0, (0, 0, 0), fpr=False)]
    for name in POLICIES:
        assert label_of([], name) is None
        assert (label_of(rejected, name) is None) == (name != "last")


def test_policies_are_a_registry_by_name():
    assert {"last", "last-fpr", "best-score", "closest-fpr", "robust-mean"} <= set(POLICIES)
    with pytest.raises(KeyError, match="unknown labelling policy 'median'"):
        label_of(HISTORY, "median")


# --- .xlsx files --------------------------------------------------------------------------------------

def sample_store(policy="robust-mean"):
    store = ObjectStore(DIMS, policy=policy)
    store.add(obs(1.0, (1.0, 0.5, 0.25), belief=7.5, yaw=0.3))
    store.add(obs(1.5, (1.01, 0.5, 0.25), belief=6.5, yaw=0.3))
    store.add(obs(2.0, (3.0, -1.0, 0.75), cls="Cookies", belief=float("nan")))
    store.add(obs(3.0, (-2.0, 4.0, 0.1), cls="E", belief=11.0, yaw=-2.0))
    return store


def assert_same_objects(a, b, history=True):
    assert [o.id for o in a] == [o.id for o in b]
    for x, y in zip(a, b):
        assert (x.cls, x.first_seen, x.last_seen, x.observations, x.edited) == \
               (y.cls, y.first_seen, y.last_seen, y.observations, y.edited)
        for f in ("xyz", "quat_xyzw", "size"):
            np.testing.assert_allclose(getattr(x, f), getattr(y, f), rtol=0, atol=1e-15)
        assert x.score == y.score or (math.isnan(x.score) and math.isnan(y.score))
        if history:
            assert [h.to_dict() for h in x.history] == [h.to_dict() for h in y.history]


def test_xlsx_round_trip_keeps_every_column(tmp_path):
    store, path = sample_store(), tmp_path / "labels.xlsx"
    store.save(path)
    loaded = ObjectStore.load(path, DIMS)
    assert_same_objects(store, loaded, history=False)
    assert list(pd.read_excel(path, sheet_name="objects").columns) == COLUMNS
    assert [p.name for p in tmp_path.iterdir()] == ["labels.xlsx"]  # no temporary file left behind


def pandas_xlsx(path, objects):
    """The store's sheet as pandas' ``to_excel`` writes it (how the store wrote it before)."""
    table = pd.DataFrame([o.row() for o in objects], columns=COLUMNS)
    with open(path, "wb") as f, pd.ExcelWriter(f, engine="openpyxl") as writer:
        table.to_excel(writer, sheet_name="objects", index=False)


def workbook_parts(path):
    """Every part of an .xlsx (a zip) by name, in order, but its creation time (docProps/core.xml)."""
    with zipfile.ZipFile(path) as z:
        return [(n, z.read(n)) for n in z.namelist() if n != "docProps/core.xml"]


def test_xlsx_holds_what_pandas_would_write(tmp_path):
    # the store writes its sheet with openpyxl itself: the same parts, byte for byte, as pandas made
    store = sample_store()
    objects = list(store)
    rng = np.random.default_rng(3)
    for i, score in enumerate([math.nan, math.inf, -math.inf, -0.0, 1e-300, 1e300, 143.5668055480008]):
        objects.append(MapObject(100 + i, ["Mustard", "Ünïcode", "a b"][i % 3], rng.normal(size=3),
                                 rng.normal(size=4), np.abs(rng.normal(size=3)), 0.1 * i, 1.3 * i, 7 * i, score,
                                 bool(i % 2), ["label", "candidate", "retired"][i % 3],
                                 ["", "1 observations (needs 5)"][i % 2], views=i % 4))
    objects[-1].xyz = np.array([math.nan, 1.0, math.inf])
    objects[-2].reason = None  # missing, as pandas writes NaN: an empty string
    for case in ([], objects[:1], objects):
        ours, theirs = tmp_path / "ours.xlsx", tmp_path / "theirs.xlsx"
        _write_xlsx(ours, case)
        pandas_xlsx(theirs, case)
        assert workbook_parts(ours) == workbook_parts(theirs)


def edit_cells(path, row, **cells):
    wb = openpyxl.load_workbook(path)
    ws = wb["objects"]
    header = [c.value for c in ws[1]]
    for column, value in cells.items():
        ws.cell(row=row, column=header.index(column) + 1).value = value
    wb.save(path)


def test_a_row_edited_by_hand_survives_the_next_save(tmp_path):
    store, path = sample_store(policy="last"), tmp_path / "labels.xlsx"
    store.save(path)
    edit_cells(path, 2, x=1.111, y=0.555, edited=True)  # row 2 = object 1 (Mustard)
    store.add(obs(5.0, (1.2, 0.5, 0.25)))  # the stack sees object 1 again, elsewhere
    store.add(obs(5.0, (3.1, -1.0, 0.75), cls="Cookies"))
    store.save(path)
    saved = {o.id: o for o in read_objects(path)}
    assert saved[1].edited and tuple(saved[1].xyz[:2]) == (1.111, 0.555)
    assert saved[2].xyz[0] == 3.1  # unedited rows follow the stack
    assert store.objects[1].edited  # the store took the edit in and no longer moves it
    store.add(obs(6.0, (1.15, 0.5, 0.25)))
    assert store.objects[1].xyz[0] == 1.111


def test_overwrite_replaces_rows_edited_by_hand(tmp_path):
    store, path = sample_store(policy="last"), tmp_path / "labels.xlsx"
    store.save(path)
    edit_cells(path, 2, x=9.0, edited=True)
    store.save(path, overwrite=True)
    saved = read_objects(path)[0]
    assert saved.xyz[0] == store.objects[1].xyz[0] == 1.01 and not saved.edited


def test_a_new_run_keeps_the_hand_edited_row_of_the_last_run_without_duplicating_it(tmp_path):
    path = tmp_path / "labels.xlsx"
    sample_store().save(path)
    edit_cells(path, 4, x=-2.05, edited=True)  # row 4 = object 3 ("E")
    rerun = ObjectStore(DIMS)  # sees the objects in another order: "E" gets id 1 this time
    rerun.add(obs(0.0, (-2.02, 4.0, 0.1), cls="E"))
    rerun.add(obs(0.5, (3.0, -1.0, 0.75), cls="Cookies"))
    rerun.add(obs(1.0, (1.0, 0.5, 0.25)))
    rerun.save(path)
    saved = read_objects(path)
    assert sorted(o.cls for o in saved) == ["Cookies", "E", "Mustard"]
    (e,) = [o for o in saved if o.cls == "E"]
    assert (e.id, e.xyz[0], e.edited) == (3, -2.05, True)
    assert len({o.id for o in saved}) == 3


@pytest.mark.parametrize("row, cells, column, message", [
    (3, {"x": "abc"}, "x", "expected a number, got 'abc'"),
    (2, {"size_y": None}, "size_y", "empty cell"),
    (4, {"qw": 5.0}, "qx..qw", "expected a unit quaternion"),
    (4, {"id": 1}, "id", "id 1 is used twice"),
    (3, {"class": "Banana"}, "class", "unknown class 'Banana'"),
    (2, {"edited": "maybe"}, "edited", "expected TRUE or FALSE"),
    (3, {"observations": 2.5}, "observations", "expected a whole number"),
    (1, {"qz": "q_z"}, "qz", "missing column"),  # header cell renamed
])
def test_a_hand_broken_spreadsheet_is_rejected_naming_row_and_column_and_left_untouched(
        tmp_path, row, cells, column, message):
    path = tmp_path / "labels.xlsx"
    sample_store().save(path)
    if row == 1:
        edit_header(path, cells)
    else:
        edit_cells(path, row, **cells)
    before = path.read_bytes()
    with pytest.raises(ObjectStoreError, match=message) as err:
        ObjectStore.load(path, DIMS)
    assert (err.value.path, err.value.row, err.value.column) == (path, row, column)
    assert f"labels.xlsx, row {row}, column '{column}'" in str(err.value)
    with pytest.raises(ObjectStoreError):
        sample_store().save(path)  # saving over it would lose the hand edits: refused too
    assert path.read_bytes() == before


def edit_header(path, renames):
    wb = openpyxl.load_workbook(path)
    for cell in wb["objects"][1]:
        cell.value = renames.get(cell.value, cell.value)
    wb.save(path)


def test_a_file_that_is_not_a_workbook_is_rejected(tmp_path):
    path = tmp_path / "labels.xlsx"
    path.write_text("id,class\n1,Mustard\n")
    with pytest.raises(ObjectStoreError, match="labels.xlsx: not a readable .xlsx workbook"):
        read_objects(path)


def test_a_save_that_fails_midway_leaves_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "labels.xlsx"
    sample_store().save(path)
    before = path.read_bytes()

    def disk_full(workbook, handle):
        handle.write(b"PK\x03\x04 half a workbook")
        raise OSError("No space left on device")

    monkeypatch.setattr(openpyxl.Workbook, "save", disk_full)
    with pytest.raises(OSError, match="No space"):
        sample_store().save(path, overwrite=True)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["labels.xlsx"]


# --- .json files ------------------------------------------------------------------------------------

def test_json_round_trip_keeps_the_observation_history(tmp_path):
    store, path = sample_store(), tmp_path / "store.json"
    store.save(path)
    loaded = ObjectStore.load(path, DIMS)
    assert_same_objects(store, loaded)
    # The history is what a policy needs: relabelling after loading gives the same label.
    assert label_of(loaded.objects[1].history, "robust-mean").xyz.tolist() == store.objects[1].xyz.tolist()


def test_json_hand_edits_survive_and_broken_files_are_named(tmp_path):
    path = tmp_path / "store.json"
    sample_store(policy="last").save(path)
    doc = json.loads(path.read_text())
    doc["objects"][0].update(z=0.3, edited=True)
    path.write_text(json.dumps(doc))
    store = sample_store(policy="last")
    store.add(obs(9.0, (1.0, 0.5, 0.2)))
    store.save(path)
    assert read_objects(path)[0].xyz[2] == 0.3

    del doc["objects"][2]["qw"]
    path.write_text(json.dumps(doc))
    before = path.read_bytes()
    with pytest.raises(ObjectStoreError, match=r"store.json, objects\[2\], field 'qw': missing field"):
        ObjectStore.load(path, DIMS)
    assert path.read_bytes() == before
