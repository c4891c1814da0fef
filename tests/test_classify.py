"""`deformnet-classify`: label files, fine-tuning on a separable toy problem, mode=predict."""

from __future__ import annotations

import dataclasses

import hydra
import numpy as np
import pandas as pd
import pytest
import torch
from helpers import pinned, tiny_deformation_model, write_bout_labels

from adjust.io import write_points3d
from deformnet.behavior.labels import bouts, read_labels, smooth
from deformnet.behavior.settings import ClassifySettings
from deformnet.behavior.tracks import read_tracks
from deformnet.body import default_mouse
from deformnet.confutil import compose, to_plain
from deformnet.paths import CONF_DIR
from deformnet.so3 import transform_points
from deformnet.tables import read_points3d_table

CLASSES = ["walk", "rear"]
TINY = ["net.hidden=8", "net.layers=1", "net.embed=8", "half_window=2"]


def _toy_session(
    tmp_path, name: str, seed: int, T: int = 360, bout: int = 40, world=None, still=False,
    size=1.0,
):  # fmt: skip
    """Alternating bouts: 'walk' (flat, moving) and 'rear' (standing, pitched up 45 deg).
    world: a rotation vector turning the whole scene (a world whose up is not z); still: the
    'walk' bouts do not move either (only the pitch, i.e. the parts' heights, tells them apart);
    size: the mouse's size (its body points scaled about their centroid; the poses are the
    model's)."""
    rng = np.random.default_rng(seed)
    body = default_mouse()
    lab = (np.arange(T) // bout + seed) % 2
    poses = np.zeros((T, 6))
    yaw = np.cumsum(rng.normal(0, 0.05, T))
    poses[:, 0] = np.where(lab == 1, 0.8, 0.0) * np.cos(yaw)  # pitch about the body x axis
    poses[:, 1] = np.where(lab == 1, 0.8, 0.0) * np.sin(yaw)
    poses[:, 2] = yaw
    step = np.where(lab == 0, 0.0 if still else 2.0, 0.0)
    poses[:, 3] = 150 + np.cumsum(step * -np.sin(yaw)) % 100
    poses[:, 4] = 150 + np.cumsum(step * np.cos(yaw)) % 100
    poses[:, 5] = 10.0
    model = torch.tensor(np.asarray(body.points))
    model = model.mean(0) + (model - model.mean(0)) * float(size)
    pts = transform_points(torch.tensor(poses), model.expand(T, -1, -1)).numpy()
    pts = pts + rng.normal(0, 0.5, pts.shape)
    if world is not None:
        from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix

        Q = rodrigues_to_matrix(torch.tensor(world, dtype=torch.float64))
        R = Q @ rodrigues_to_matrix(torch.tensor(poses[:, :3]))
        poses = np.concatenate((matrix_to_rodrigues(R).numpy(), poses[:, 3:] @ Q.numpy().T), 1)
        pts = pts @ Q.numpy().T
    K = body.num_parts
    extra = {c: poses[:, i] for i, c in enumerate(("pose_rx", "pose_ry", "pose_rz"))}
    extra |= {c: poses[:, 3 + i] for i, c in enumerate(("pose_tx", "pose_ty", "pose_tz"))}
    tracks = write_points3d(
        tmp_path / f"{name}.csv",
        body.parts,
        pts,
        np.zeros((T, K)),
        np.full((T, K), 2),
        np.ones((T, K)),
        extra=extra,
        fnum=np.arange(T) + 5,
    )
    labels = write_bout_labels(tmp_path / f"{name}_labels.csv", lab, CLASSES, first=5)
    return tracks, labels, lab


def _compose(overrides):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("classify", overrides=pinned(overrides))


def _files(split: str, sessions) -> list[str]:
    t = ",".join(str(s[0]) for s in sessions)
    lab = ",".join(str(s[1]) for s in sessions)
    return [f"data.{split}_tracks=[{t}]", f"data.{split}_labels=[{lab}]"]


def test_read_labels_frames_and_bouts(tmp_path):
    fnum = np.arange(10, 20)
    p = tmp_path / "frames.csv"
    p.write_text("fnum,label\n10,walk\n11,rear\n15,rear\n")
    want = np.full(10, -1)
    want[[0, 1, 5]] = [0, 1, 1]
    np.testing.assert_array_equal(read_labels(p, fnum, CLASSES), want)
    b = tmp_path / "bouts.csv"
    b.write_text("start,stop,label\n10,12,walk\n13,19,rear\n")
    np.testing.assert_array_equal(read_labels(b, fnum, CLASSES), [0] * 3 + [1] * 7)


@pytest.mark.parametrize(
    "text, match",
    [
        ("fnum,label\n10,walk\n11,swim\n", r"bad.csv: row 2: unknown label 'swim'"),
        ("start,stop,label\n10,14,walk\n14,16,rear\n", r"bad.csv: row 2: bout 14-16 overlaps"),
        ("start,stop,label\n10,25,walk\n", r"bad.csv: row 1: frame 25 is outside track.csv"),
        ("fnum,label\n10,walk\n3,rear\n", r"bad.csv: row 2: frame 3 is outside"),
        ("fnum,label\n10,walk\n10,rear\n", r"bad.csv: row 2: frame 10 is labelled again"),
        ("start,stop,label\n14,12,walk\n", r"bad.csv: row 1: stop 12 < start 14"),
        ("frame,behavior\n10,walk\n", r"bad.csv: expected columns"),
    ],
)
def test_label_file_errors_name_file_and_row(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_labels(p, np.arange(10, 20), CLASSES, tracks="track.csv")


def test_read_tracks_needs_poses_or_complete_points(tmp_path):
    tracks, _, _ = _toy_session(tmp_path, "s", 0, T=30)
    body = default_mouse()
    full = read_tracks(tracks, body)
    df = pd.read_csv(tracks).drop(columns=[c for c in pd.read_csv(tracks) if c.startswith("pose")])
    df.loc[3, "nose_tip_x"] = np.nan
    p = tmp_path / "nopose.csv"
    df.to_csv(p, index=False)
    with pytest.raises(ValueError, match=r"nopose.csv: no pose columns and part 'nose_tip'"):
        read_tracks(p, body)
    # linear gap filling + Kabsch poses: rigid points close to those of the true poses
    filled = read_tracks(p, body, interpolate=True)
    assert np.abs(filled["rigid"] - full["rigid"]).max() < 3.0
    assert filled["observed"].all()


def test_smoothing_and_bouts():
    probs = np.zeros((20, 2))
    probs[:, 0] = 1.0
    probs[8:10] = [0.0, 1.0]  # a 2-frame blip
    assert bouts(probs.argmax(-1)) == [(0, 7, 0), (8, 9, 1), (10, 19, 0)]
    assert (smooth(probs, min_bout=3) == 0).all()
    assert (smooth(probs, median=5) == 0).all()
    assert (smooth(probs) == probs.argmax(-1)).all()


def test_fine_tuning_separates_two_behaviors_and_predict_round_trips(tmp_path):
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    val = [_toy_session(tmp_path, "val", 7)]
    test = [_toy_session(tmp_path, "test", 8)]
    out = tmp_path / "fit"
    cfg = _compose(
        [
            *TINY,
            f"classes=[{','.join(CLASSES)}]",
            "label_fraction=0.25",
            *_files("train", train),
            *_files("val", val),
            *_files("test", test),
            "data.batch_size=32",
            "data.steps_per_epoch=10",
            "trainer.max_epochs=6",
            "trainer.max_time=null",
            "logger=none",
            "smoothing.median=0",
            "smoothing.min_bout=0",
            f"output.dir={out}",
        ]
    )
    res = run(cfg)
    rep = res["report"]
    assert rep["split"] == "test"
    assert rep["labelled_training_frames"] == 2 * 90  # 25% of 360 frames per session
    assert rep["raw"]["macro_f1"] >= 0.95, rep["raw"]
    assert rep["raw"]["per_class"]["rear"]["recall"] >= 0.95
    assert rep["bouts"]["true"]["walk"]["bouts"] == 5
    for f in ("classifier.pt", "report.json", "confusion.png", "ethogram.png"):
        assert (out / f).exists()

    # mode=predict on the test track: labels + probabilities, and bouts that read back
    pred_dir = tmp_path / "pred"
    p = run(
        _compose(
            [
                "mode=predict",
                f"checkpoint={out / 'classifier.pt'}",
                f"tracks={test[0][0]}",
                f"output.dir={pred_dir}",
            ]
        )
    )
    df = pd.read_csv(p["predictions"])
    assert df["fnum"].tolist() == list(range(5, 365))
    np.testing.assert_allclose(df[["p_walk", "p_rear"]].sum(1), 1.0, atol=1e-5)
    per_frame = read_labels(p["predictions"], df["fnum"].to_numpy(), CLASSES)
    from_bouts = read_labels(p["bouts"], df["fnum"].to_numpy(), CLASSES)
    np.testing.assert_array_equal(per_frame, from_bouts)
    assert np.mean(per_frame == test[0][2]) >= 0.95
    bdf = pd.read_csv(p["bouts"])
    assert list(bdf.columns) == ["start", "stop", "label", "mean_probability"]
    assert ((bdf["mean_probability"] > 0.5) & (bdf["mean_probability"] <= 1.0)).all()

    # the same track with a user's own part names: loose matches (case, separators) and the
    # model's aliases need nothing; the others are an error naming them, until aliases= maps them
    names = {"nose_tip": "Snout", "left_ear": "Ear_L", "right_ear": "RightEar",
             "left_front_paw": "LFP", "right_front_paw": "Right-Front-Paw",
             "left_hind_paw": "hl", "tail_root": "TailBase"}  # fmt: skip
    df0 = read_points3d_table(test[0][0])  # with the sidecar's pose columns, as one table
    mine = df0.rename(columns={c: names[p] + c[len(p):] for c in df0.columns for p in names
                               if c.startswith(p + "_")})  # fmt: skip
    renamed = tmp_path / "renamed.csv"
    mine.to_csv(renamed, index=False)
    base = ["mode=predict", f"checkpoint={out / 'classifier.pt'}", f"tracks={renamed}"]
    with pytest.raises(ValueError, match=r"renamed.csv: no .* part\(s\) \['left_front_paw', "
                       r"'left_hind_paw'\] .*other parts: \['LFP', 'hl'\]"):  # fmt: skip
        run(_compose([*base, f"output.dir={tmp_path / 'bad'}"]))
    q = run(_compose([*base, "aliases={LFP: left_front_paw, hl: left_hind_paw}",
                      f"output.dir={tmp_path / 'mine'}"]))  # fmt: skip
    pd.testing.assert_frame_equal(pd.read_csv(q["predictions"]), df)
    both = pd.concat([df0, mine[[c for c in mine.columns if c.startswith("Snout_")]]], axis=1)
    both.to_csv(renamed, index=False)
    with pytest.raises(ValueError, match=r"parts 'nose_tip' and 'Snout' both map to body part"):
        run(_compose([*base, f"output.dir={tmp_path / 'bad2'}"]))


def _fit_from_pretrained(tmp_path, overrides: list[str], up=None):
    """Fine-tune from a saved tiny deformation net (seed 3; up: its heading frame) on one toy
    session (3 steps an epoch); returns that net, its checkpoint path and the run's result."""
    from deformnet.behavior.predict import run

    ckpt = tmp_path / "net.ckpt"
    pre = tiny_deformation_model(seed=3, up=up)
    pre.save(ckpt)
    train = [_toy_session(tmp_path, "train", 0, T=120)]
    res = run(
        _compose(
            [
                f"pretrained={ckpt}",
                *overrides,
                f"classes=[{','.join(CLASSES)}]",
                *_files("train", train),
                "data.batch_size=16",
                "data.steps_per_epoch=3",
                "logger=none",
                f"output.dir={tmp_path / 'fit'}",
            ]
        )
    )
    return pre, ckpt, res


def test_pretrained_frozen_encoder_is_kept(tmp_path):
    from deformnet.behavior.model import load_classifier

    pre, ckpt, res = _fit_from_pretrained(tmp_path, ["freeze=true", "trainer.max_epochs=1"])
    model, meta = load_classifier(res["checkpoint"])
    assert meta["pretrained"] == str(ckpt) and meta["freeze"]
    for k, v in pre.net.state_dict().items():
        torch.testing.assert_close(model.encoder.net.state_dict()[k], v)
    assert res["report"]["split"] == "train"


def test_heading_frame_encoder_is_carried_into_the_classifier_and_predict(tmp_path):
    """A net pretrained in the heading frame (up = z): the classifier reads windows in that
    frame, its checkpoint says so, and predicting from the checkpoint gives the same
    probabilities as the trained model."""
    from deformnet.behavior.features import SessionBank
    from deformnet.behavior.model import features_probs, load_classifier
    from deformnet.behavior.predict import run

    pre, ckpt, res = _fit_from_pretrained(
        tmp_path, ["freeze=true", "trainer.max_epochs=1"], up=(0, 0, 1)
    )
    model, meta = load_classifier(res["checkpoint"])
    assert meta["up"] == [0.0, 0.0, 1.0] and model.encoder.up == (0.0, 0.0, 1.0)
    body_frame, _ = load_classifier(res["checkpoint"])
    body_frame.encoder.up = None  # the same weights reading the body frame: other outputs
    test = _toy_session(tmp_path, "test", 9, T=60)
    from deformnet.behavior.predict import read_session

    s = read_session(str(test[0]), model, meta)  # as mode=predict reads it (body scale set)
    assert meta["body_scale"] == "session" and s.scale is not None
    bank = SessionBank([s], model.half_window)
    p_head = features_probs(model, bank)[1]
    assert np.abs(p_head - features_probs(body_frame, bank)[1]).max() > 1e-4
    out = run(
        _compose(
            [
                "mode=predict",
                f"checkpoint={res['checkpoint']}",
                f"tracks={test[0]}",
                f"output.dir={tmp_path / 'pred'}",
            ]
        )
    )
    df = pd.read_csv(out["predictions"])
    np.testing.assert_allclose(df[[f"p_{c}" for c in CLASSES]].to_numpy(), p_head, atol=1e-5)
    # tracks from a world whose up is y, not z: refused, naming the file
    sideways = _toy_session(tmp_path, "sideways", 0, T=120, world=[-np.pi / 2, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"sideways.csv: the deformation net reads .* 90 deg"):
        run(_compose(["mode=predict", f"checkpoint={res['checkpoint']}",
                      f"tracks={sideways[0]}", f"output.dir={tmp_path / 'pred2'}"]))  # fmt: skip
    # scratch: the config's up
    res2 = run(
        _compose(
            [
                "pretrained=null",
                "up=[0,0,1]",
                f"classes=[{','.join(CLASSES)}]",
                *_files("train", [_toy_session(tmp_path, "train", 0, T=120)]),
                "data.batch_size=16",
                "data.steps_per_epoch=2",
                "trainer.max_epochs=1",
                "logger=none",
                f"output.dir={tmp_path / 'scratch'}",
            ]
        )
    )
    assert load_classifier(res2["checkpoint"])[1]["up"] == [0.0, 0.0, 1.0]
    with pytest.raises(ValueError, match=r"up=\[0, 1, 0\] but the pretrained net .* reads "
                       r"up=\[0.0, 0.0, 1.0\]"):  # fmt: skip
        run(_compose([f"pretrained={ckpt}", "up=[0,1,0]", f"output.dir={tmp_path / 'bad'}"]))
    with pytest.raises(ValueError, match="up must be"):
        run(_compose(["pretrained=null", "up=[0,0,0]", *_files("train", []) ,
                      f"output.dir={tmp_path / 'bad'}"]))  # fmt: skip


def test_pretrained_probe_then_fine_tune_changes_the_encoder(tmp_path):
    from deformnet.behavior.model import load_classifier

    pre, _, res = _fit_from_pretrained(tmp_path, ["freeze=false", "trainer.max_epochs=2"])
    assert res["report"]["probe"]["iterations"] > 0  # the head's L-BFGS probe first
    assert res["report"]["training_steps"] == 2 * 3  # then fine-tuning
    # no validation sessions: the last state is kept (not a best-validation one)
    model, _ = load_classifier(res["checkpoint"])
    changed = [
        k
        for k, v in pre.net.state_dict().items()
        if not torch.equal(model.encoder.net.state_dict()[k], v)
    ]
    assert any(k.startswith("lstm.") for k in changed)


def test_lbfgs_probe_is_logistic_regression():
    """fit_head_lbfgs on a linear head = multinomial logistic regression with C = 1 / l2
    (scikit-learn's, class-weighted), on the head's standardised inputs."""
    from sklearn.linear_model import LogisticRegression

    from deformnet.behavior.fit import fit_head_lbfgs
    from deformnet.behavior.heads import LinearHead

    g = np.random.default_rng(0)
    N, D, C = 300, 6, 3
    y = g.integers(0, C, N)
    y[:150] = 0  # imbalanced
    X = g.normal(size=(N, D)) + np.eye(C, D)[y] * 1.5

    class Probe(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.head = LinearHead(D, C, norm=False)
            self.register_buffer("feature_mean", torch.zeros(D))
            self.register_buffer("feature_std", torch.ones(D))

        def classify(self, f):
            return self.head((f - self.feature_mean) / self.feature_std)

    counts = np.bincount(y, minlength=C)
    w = counts.sum() / (C * counts)
    m = Probe()
    facts = fit_head_lbfgs(m, torch.tensor(X, dtype=torch.float32), torch.tensor(y), w, l2=2.0)
    ref = LogisticRegression(C=0.5, class_weight="balanced", tol=1e-10, max_iter=5000).fit(X, y)
    with torch.no_grad():
        logits = m.classify(torch.tensor(X, dtype=torch.float32)).numpy()
    lin = m.head.net[-1]
    W = lin.weight.detach().numpy()
    # softmax logits are defined up to a per-sample constant: compare centred
    np.testing.assert_allclose(W - W.mean(0), ref.coef_ - ref.coef_.mean(0), atol=2e-3)
    np.testing.assert_array_equal(logits.argmax(-1), ref.predict(X))
    assert facts["iterations"] > 0 and facts["loss"] > 0


def test_forest_head_on_a_frozen_encoder_and_predict(tmp_path):
    """head=forest (freeze=true): fitted on the labelled frames' features, stored in
    classifier.pt, and mode=predict reloads it and labels the test track."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = [_toy_session(tmp_path, "test", 8)]
    base = [
        *TINY,
        "head=forest",
        "head.trees=25",
        f"classes=[{','.join(CLASSES)}]",
        "label_fraction=0.05",
        *_files("train", train),
        *_files("test", test),
        "logger=none",
        "smoothing.median=0",
        "smoothing.min_bout=0",
    ]
    with pytest.raises(ValueError, match="freeze=true"):
        run(_compose([*base, "freeze=false", f"output.dir={tmp_path / 'no'}"]))
    with pytest.raises(ValueError, match="head=forest reads the frame features"):
        run(
            _compose(
                [*base, "freeze=true", "frame_features=false", f"output.dir={tmp_path / 'no'}"]
            )
        )
    out = tmp_path / "forest"
    rep = run(_compose([*base, "freeze=true", f"output.dir={out}"]))["report"]
    assert rep["labelled_training_frames"] == 2 * 18
    assert rep["head_solver"] == "forest" and rep["probe"]["trees"] == 25
    assert rep["raw"]["macro_f1"] >= 0.95, rep["raw"]
    model, meta = load_classifier(out / "classifier.pt")
    assert meta["head"]["name"] == "forest" and int(model.head.roots.numel()) == 25
    p = run(
        _compose(
            [
                "mode=predict",
                f"checkpoint={out / 'classifier.pt'}",
                f"tracks={test[0][0]}",
                f"output.dir={tmp_path / 'pred'}",
            ]
        )
    )
    df = pd.read_csv(p["predictions"])
    np.testing.assert_allclose(df[["p_walk", "p_rear"]].sum(axis=1), 1.0, atol=1e-5)
    assert np.mean(df["label"].to_numpy() == np.asarray(CLASSES)[test[0][2]]) >= 0.95


def _box_session(tmp_path, name: str, seed: int, at, away, T: int = 240, bout: int = 40):
    """A still mouse whose two behaviors differ only by where it stands: 'lever' with its snout
    at the mechanism `at`, 'walk' (here: standing) at `away`; same pose and jitter, so only the
    lock-box context tells them apart. Returns (tracks, labels, per-frame labels)."""
    rng = np.random.default_rng(seed)
    body = default_mouse()
    lab = (np.arange(T) // bout + seed) % 2  # 1: at the lever
    model = torch.tensor(np.asarray(body.points))
    nose = np.asarray(body.points)[body.parts.index("nose_tip")]
    poses = np.zeros((T, 6))
    poses[:, 2] = rng.normal(0, 0.05, T)
    spot = np.where(lab[:, None] == 1, np.asarray(at) - nose, np.asarray(away) - nose)
    poses[:, 3:] = spot + rng.normal(0, 1.0, (T, 3))
    pts = transform_points(torch.tensor(poses), model.expand(T, -1, -1)).numpy()
    pts = pts + rng.normal(0, 0.5, pts.shape)
    K = body.num_parts
    extra = {c: poses[:, i] for i, c in enumerate(POSE)}
    tracks = write_points3d(tmp_path / f"{name}.csv", body.parts, pts, np.zeros((T, K)),
                            np.full((T, K), 2), np.ones((T, K)), extra=extra)  # fmt: skip
    names = ["walk", "lever"]
    labels = tmp_path / f"{name}_labels.csv"
    pd.DataFrame([{"start": a, "stop": b, "label": names[c]} for a, b, c in bouts(lab)]).to_csv(
        labels, index=False
    )
    return tracks, labels, lab


POSE = ("pose_rx", "pose_ry", "pose_rz", "pose_tx", "pose_ty", "pose_tz")


def _calibration(path, mechanisms: dict) -> str:
    rows = "\n".join(
        f"{k} = [{', '.join(str(float(v)) for v in p)}]" for k, p in mechanisms.items()
    )
    path.write_text(f"[metadata.mechanisms]\n{rows}\n")
    return str(path)


def test_lock_box_context_tells_apart_what_only_the_place_does(tmp_path):
    """mechanisms.calibration: two behaviors with the same still pose, one at the lever and one
    away from it, in a world where the encoder's canonical frame and no pose features are read
    (frame_features=false): without the lock-box context the classifier cannot tell them
    apart, with it it does; mode=predict on a recording whose lock box stands elsewhere reads
    that recording's positions (mechanisms.calibration) and stays right, while the training
    rig's positions would not be."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    lever, ball = [200.0, 250.0, 12.0], [120.0, 250.0, 10.0]
    away = [80.0, 120.0, 12.0]
    calib = _calibration(tmp_path / "calibration.toml", {"lever": lever, "ball": ball})
    train = [_box_session(tmp_path, f"train{i}", i, lever, away) for i in range(2)]
    test = [_box_session(tmp_path, "test", 5, lever, away)]
    common = [
        *TINY,
        "freeze=true",
        "frame_features=false",
        "classes=[walk,lever]",
        "label_fraction=0.1",
        *_files("train", train),
        *_files("test", test),
        "logger=none",
        "smoothing.median=0",
        "smoothing.min_bout=0",
    ]
    base = [*common, "head=forest", "head.trees=25"]
    with pytest.raises(ValueError, match="head=forest reads the frame features"):
        run(_compose([*base, f"output.dir={tmp_path / 'none'}"]))
    # a linear head reads the encoder's canonical outputs (no pose, no place)
    blind = run(_compose([*common, "head=linear", f"output.dir={tmp_path / 'blind'}"]))
    assert blind["report"]["raw"]["macro_f1"] < 0.8, blind["report"]["raw"]
    out = tmp_path / "box"
    res = run(_compose([*base, f"mechanisms.calibration={calib}", f"output.dir={out}"]))
    assert res["report"]["raw"]["macro_f1"] >= 0.95, res["report"]["raw"]
    assert res["report"]["mechanisms"]["names"] == ["lever", "ball"]
    model, meta = load_classifier(out / "classifier.pt")
    assert meta["mechanisms"]["names"] == ["lever", "ball"]
    assert meta["mechanisms"]["parts"] == ["nose_tip", "left_front_paw", "right_front_paw"]
    assert model.encoder.mechanisms.out_dim == 2 * 4

    # a second rig: the lock box 300 mm further along x
    moved = {"lever": [lever[0] + 300, *lever[1:]], "ball": [ball[0] + 300, *ball[1:]]}
    far = _box_session(tmp_path, "moved", 6, moved["lever"], [away[0] + 300, *away[1:]])
    calib2 = _calibration(tmp_path / "calibration2.toml", moved)

    def accuracy(extra, tag):
        p = run(_compose(["mode=predict", f"checkpoint={out / 'classifier.pt'}",
                          f"tracks={far[0]}", f"output.dir={tmp_path / tag}", *extra]))  # fmt: skip
        df = pd.read_csv(p["predictions"])
        return float(np.mean(df["label_raw"].to_numpy() == np.array(["walk", "lever"])[far[2]]))

    assert accuracy([f"mechanisms.calibration={calib2}"], "p2") >= 0.95
    assert accuracy([], "p1") < 0.8  # the training rig's positions: wrong for this recording
    with pytest.raises(ValueError, match=r"no position for mechanism\(s\) \['ball'\]"):
        accuracy([f"mechanisms.positions={{lever: {moved['lever']}}}"], "p3")
    with pytest.raises(ValueError, match="trained without lock-box context"):
        run(_compose(["mode=predict", f"checkpoint={tmp_path / 'blind' / 'classifier.pt'}",
                      f"tracks={far[0]}", f"mechanisms.calibration={calib2}",
                      f"output.dir={tmp_path / 'p4'}"]))  # fmt: skip


@pytest.mark.parametrize(
    "overrides, match",
    [
        (["mechanisms.positions={lever: [1, 2]}"], r"mechanism 'lever' needs \[x, y, z\]"),
        (["mechanisms.positions={lever: [1, 2, 3]}", "mechanisms.parts=[tail_tip]"],
         "unknown body part 'tail_tip'"),
        (["mechanisms.positions={lever: [1, 2, 3]}", "mechanisms.calibration=x.toml"],
         "not both"),
        (["mechanisms.calibration=missing.toml"], "file not found: missing.toml"),
        (["mechanisms.positions={lever: [1, 2, 3]}", "mechanisms.scale=0"], "scale must be > 0"),
    ],
)  # fmt: skip
def test_mechanism_config_errors(overrides, match):
    from deformnet.behavior.model import mechanism_setup
    from deformnet.body import BodyModel

    cfg = _compose(overrides)
    with pytest.raises(ValueError, match=match):
        mechanism_setup(ClassifySettings.from_config(cfg), BodyModel.from_config(cfg.body))


def test_mechanism_setup_sources(tmp_path):
    """positions=sim: the default simulator's lock box; a calibration without the table is
    named."""
    from deformnet.behavior.model import mechanism_setup
    from deformnet.body import BodyModel
    from deformnet.sim import MECHANISMS, simulate

    cfg = _compose(["mechanisms.positions=sim", "mechanisms.parts=[snout]"])
    body = BodyModel.from_config(cfg.body)
    m = mechanism_setup(ClassifySettings.from_config(cfg), body)
    data = simulate(None, num_frames=30, seed=0, body=body)
    assert m["names"] == list(MECHANISMS) and m["parts"] == ["nose_tip"]
    np.testing.assert_allclose(m["positions"], data.mechanism_positions)
    bad = tmp_path / "calibration.toml"
    bad.write_text("[cam_0]\nname = 'a'\n")
    with pytest.raises(ValueError, match=r"calibration.toml: no \[metadata.mechanisms\] table"):
        mechanism_setup(ClassifySettings.from_config(_compose([f"mechanisms.calibration={bad}"])),
                        body)  # fmt: skip
    assert mechanism_setup(ClassifySettings.from_config(_compose([])), body) is None


def test_the_settings_the_recipe_reads_are_typed_with_the_yamls_defaults():
    """conf/classify.yaml's defaults are ClassifySettings' (the one copy in the code), every
    field a key of the YAML (but the optional +sim block; of ``data``, the keys with a default);
    an absent key, or a block given as null, keeps them; given ones are read (a whole number
    as an integer); a bad value is named."""
    yaml, st = compose("classify"), ClassifySettings()
    names = lambda obj: {f.name for f in dataclasses.fields(obj)}  # noqa: E731
    assert names(st) - set(yaml) == {"sim"}
    for block in ("context", "mechanisms", "unfamiliar", "smoothing", "pseudo_labels"):
        assert names(getattr(st, block)) == set(yaml[block]), block
    assert names(st.pseudo_labels.sequence) == set(yaml.pseudo_labels.sequence)
    assert names(st.data) <= set(yaml.data)
    for block in ("context", "mechanisms", "unfamiliar", "smoothing", "data", "pseudo_labels"):
        plain = to_plain(yaml[block])
        for k, v in dataclasses.asdict(getattr(st, block)).items():
            assert v == plain[k], f"{block}.{k}: {v!r} here, {plain[k]!r} in the YAML"
    assert ClassifySettings.from_config(yaml) == st  # and the top-level keys
    assert ClassifySettings.from_config({}) == st
    assert ClassifySettings.from_config({"context": None, "unfamiliar": None}) == st
    assert ClassifySettings.from_config({"pseudo_labels": {"sequence": None}}) == st
    given = ClassifySettings.from_config(
        _compose(["body_scale=none", "context.frames=[]", "mechanisms.scale=20",
                  "unfamiliar.warn_share=0.3", "head_max_iter=5", "pseudo_labels.teacher=none",
                  "pseudo_labels.sequence.steps=30.0", "pseudo_labels.sequence.encoder=a.pt",
                  "data.interpolate=true", "data.token_dropout=0"])
    )  # fmt: skip
    assert (given.body_scale, given.context.frames, given.context.stride) == ("none", [], 1)
    assert (given.mechanisms.scale, given.unfamiliar.warn_share) == (20, 0.3)
    assert given.head_max_iter == 5 and given.mechanisms.parts == st.mechanisms.parts
    pl = given.pseudo_labels
    assert (pl.teacher, pl.keep, pl.sequence.encoder) == ("none", 0.3, "a.pt")
    assert pl.sequence.steps == 30 and isinstance(pl.sequence.steps, int)
    assert given.data == dataclasses.replace(st.data, interpolate=True, token_dropout=0.0)
    with pytest.raises(ValueError, match=r"unfamiliar.warn_share must be in \[0, 1\), got 1.5"):
        ClassifySettings.from_config(_compose(["unfamiliar.warn_share=1.5"]))
    with pytest.raises(ValueError, match=r"pseudo_labels.sequence.dilations must be a non-empty"):
        ClassifySettings.from_config(_compose(["pseudo_labels.sequence.dilations=[]"]))
    with pytest.raises(ValueError, match="pseudo_labels.labelled_weight must be a number > 0"):
        ClassifySettings.from_config({"pseudo_labels": {"labelled_weight": True}})


def test_heights_up_gives_a_body_frame_encoder_the_part_heights(tmp_path):
    """A toy that only the parts' heights solve (a still mouse, flat or pitched up; a rigid body
    has constant part distances): a body-frame encoder's measurements with heights_up reach a
    high F1, without it (no heights) about chance; heights_up is stored and mode=predict uses it
    (and checks the recording's world against it); heights_up without measurements is an error."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i, still=True) for i in range(2)]
    test = [_toy_session(tmp_path, "test", 8, still=True)]

    def fit(extra, out):
        return run(
            _compose(
                [*TINY, "head=forest", "head.trees=25", "freeze=true", "frame_features=false",
                 "measurements=true", f"classes=[{','.join(CLASSES)}]",
                 "label_fraction=0.25", "context.frames=[]", *_files("train", train),
                 *_files("test", test), "logger=none", "smoothing.median=0",
                 "smoothing.min_bout=0", f"output.dir={out}", *extra]
            )
        )["report"]["raw"]["macro_f1"]  # fmt: skip

    out = tmp_path / "heights"
    assert fit(["heights_up=[0,0,2]"], out) >= 0.95
    assert fit([], tmp_path / "no_heights") <= 0.7  # distances constant, speeds only noise
    model, meta = load_classifier(out / "classifier.pt")
    assert meta["heights_up"] == [0.0, 0.0, 1.0] and model.encoder.up is None
    p = run(_compose(["mode=predict", f"checkpoint={out / 'classifier.pt'}",
                      f"tracks={test[0][0]}", f"output.dir={tmp_path / 'pred'}"]))  # fmt: skip
    df = pd.read_csv(p["predictions"])
    assert np.mean(df["label_raw"].to_numpy() == np.asarray(CLASSES)[test[0][2]]) >= 0.95
    sideways = _toy_session(tmp_path, "sideways", 9, still=True, world=[np.pi / 2, 0.0, 0.0])
    with pytest.raises(ValueError, match="sideways.csv"):
        run(_compose(["mode=predict", f"checkpoint={out / 'classifier.pt'}",
                      f"tracks={sideways[0]}", f"output.dir={tmp_path / 'pred2'}"]))  # fmt: skip
    with pytest.raises(ValueError, match="heights_up .*measurements=true"):
        run(_compose([*TINY, "heights_up=[0,0,1]", *_files("train", train), "logger=none",
                      f"output.dir={tmp_path / 'bad'}"]))  # fmt: skip


def test_feature_range_and_unfamiliar_share():
    """feature_range: each feature's q / 1 - q quantiles over the frames, widened by a margin
    (by default shrinking with the frames); unfamiliar_share: per frame the share of its
    features outside them; shapes and bad input are checked."""
    from deformnet.behavior.features import feature_range, unfamiliar_share

    x = torch.arange(1000, dtype=torch.float32)[:, None].repeat(1, 4)  # 0..999 in every column
    x[:, 1] *= 2
    rng = feature_range(x, 0.01, margin=0.0)
    torch.testing.assert_close(rng["low"], torch.tensor([9.99, 19.98, 9.99, 9.99]))
    torch.testing.assert_close(rng["high"], torch.tensor([989.01, 1978.02, 989.01, 989.01]))
    # the default margin: 0.1 sqrt(3000 / N) of the quantiles' distance on each side
    wide = feature_range(x, 0.01)
    m = 0.1 * (3000 / 1000) ** 0.5
    assert wide["margin"] == pytest.approx(m) and wide["frames"] == 1000
    torch.testing.assert_close(wide["low"][0], torch.tensor(9.99 - m * 979.02))
    torch.testing.assert_close(wide["high"][1], torch.tensor(1978.02 + m * 1958.04))
    y = torch.tensor([[500.0, 1000.0, 500.0, 500.0], [0.0, 1000.0, 995.0, 500.0],
                      [-1.0, 5000.0, 2000.0, 0.0]])  # fmt: skip
    np.testing.assert_allclose(unfamiliar_share(y, rng), [0.0, 0.5, 1.0])
    with pytest.raises(ValueError, match=r"features must be \(N, 4\)"):
        unfamiliar_share(y[:, :3], rng)
    with pytest.raises(ValueError, match="N >= 2"):
        feature_range(x[:1])


def test_predict_warns_on_a_recording_unlike_the_training_data(tmp_path, caplog):
    """classifier.pt stores the training frames' feature range; mode=predict on a recording like
    them flags almost no frame, on a mouse 1.5x the size (another animal; the classifier does
    not divide the size out, body_scale=none) most frames, and then warns in the log and
    summary.json; the per-frame share is the predictions' `unfamiliar`."""
    import json
    import logging

    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = [_toy_session(tmp_path, "test", 8)]
    out = tmp_path / "cls"
    rep = run(
        _compose(
            [*TINY, "freeze=true", f"classes=[{','.join(CLASSES)}]",
             *_files("train", train), *_files("test", test), "logger=none",
             f"output.dir={out}", "body_scale=none"]
        )
    )["report"]  # fmt: skip
    assert rep["unfamiliar_frames"] <= 0.05 and rep["body_scales"] is None
    _, meta = load_classifier(out / "classifier.pt")
    assert meta["feature_range"]["low"].shape == meta["feature_range"]["high"].shape
    same = _toy_session(tmp_path, "same", 9)
    big = _toy_session(tmp_path, "big", 9, size=1.5)
    res = {}
    for name, (tracks, *_) in (("same", same), ("big", big)):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="deformnet.behavior"):
            ov = ["mode=predict", f"checkpoint={out / 'classifier.pt'}", f"tracks={tracks}"]
            res[name] = run(_compose([*ov, f"output.dir={tmp_path / name}"]))
        res[name]["log"] = caplog.text
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert summary["unfamiliar_frames"] == pytest.approx(res[name]["unfamiliar_frames"])
    assert res["same"]["unfamiliar_frames"] <= 0.05 and res["same"]["warning"] is None
    assert "unlike the classifier's training data" not in res["same"]["log"]
    assert res["big"]["unfamiliar_frames"] >= 0.5
    assert "big.csv" in res["big"]["warning"] and "unlike" in res["big"]["log"]
    df = pd.read_csv(res["big"]["predictions"])
    assert np.mean(df["unfamiliar"] > 0.05) == pytest.approx(res["big"]["unfamiliar_frames"])


def test_body_scale_lets_a_classifier_label_a_larger_mouse(tmp_path):
    """body_scale=session (the default): each session's size against the body model is
    measured (the report, classifier.pt) and divided out, so a mouse 1.5x the size is labelled
    like the model-size mouse (the same poses): the same labels, no unfamiliar frames, its
    scale in summary.json. A bad body_scale and a track in metres are errors naming them."""
    import json

    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = [_toy_session(tmp_path, "test", 8)]
    out = tmp_path / "cls"
    ov = [*TINY, "freeze=true", f"classes=[{','.join(CLASSES)}]",
          *_files("train", train), "logger=none"]  # fmt: skip
    rep = run(_compose([*ov, *_files("test", test), f"output.dir={out}"]))["report"]
    assert rep["body_scales"] and all(abs(v - 1) < 0.01 for v in rep["body_scales"].values())
    assert load_classifier(out / "classifier.pt")[1]["body_scale"] == "session"
    res = {}
    for name, size in (("same", 1.0), ("big", 1.5)):
        tracks = _toy_session(tmp_path, name, 9, size=size)[0]
        pred = ["mode=predict", f"checkpoint={out / 'classifier.pt'}", f"tracks={tracks}"]
        res[name] = run(_compose([*pred, f"output.dir={tmp_path / name}"]))
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert summary["body_scale"] == pytest.approx(size, abs=0.01)
    assert res["big"]["warning"] is None and res["big"]["unfamiliar_frames"] <= 0.05
    same, big = (pd.read_csv(res[n]["predictions"]) for n in ("same", "big"))
    assert np.mean(same["label"] == big["label"]) >= 0.95
    # the same track posed with another body model (its own axes, as body=auto's): the pose is
    # refitted to the classifier's model, so the labels stay the same
    from deformnet.behavior.tracks import POSE_COLUMNS

    other = read_points3d_table(_toy_session(tmp_path, "same", 9)[0])  # with the pose sidecar
    Q = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])
    body = default_mouse()
    other[list(POSE_COLUMNS)] = _other_model_poses(
        other[list(POSE_COLUMNS)].to_numpy(), body, Q, np.zeros(3)
    )
    other.to_csv(tmp_path / "other.csv", index=False)
    pred = ["mode=predict", f"checkpoint={out / 'classifier.pt'}"]
    pred += [f"tracks={tmp_path / 'other.csv'}", f"output.dir={tmp_path / 'other'}"]
    got = run(_compose(pred))
    assert json.loads((tmp_path / "other" / "summary.json").read_text())["pose"] == "fitted"
    assert json.loads((tmp_path / "same" / "summary.json").read_text())["pose"] == "columns"
    assert np.mean(pd.read_csv(got["predictions"])["label"] == same["label"]) >= 0.95
    assert got["warning"] is None
    with pytest.raises(ValueError, match="body_scale must be one of"):
        run(_compose([*ov, "body_scale=size", f"output.dir={tmp_path / 'bad'}"]))
    metres = read_points3d_table(test[0][0])
    xyz = [c for c in metres.columns if c[-2:] in ("_x", "_y", "_z") and not c.startswith("pose")]
    metres[xyz] = metres[xyz] / 1000.0
    metres.to_csv(tmp_path / "metres.csv", index=False)
    with pytest.raises(ValueError, match=r"metres.csv: the tracked parts are .* in mm"):
        pred = ["mode=predict", f"checkpoint={out / 'classifier.pt'}"]
        run(_compose([*pred, f"tracks={tmp_path / 'metres.csv'}", f"output.dir={tmp_path / 'm'}"]))


def test_measurements_alone_feed_a_forest_and_predict_round_trips(tmp_path):
    """measurements=true with no other frame features: the forest reads the part speeds and
    distances (walk moves, rear stands), the flag is stored in classifier.pt and mode=predict
    rebuilds the same features."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = [_toy_session(tmp_path, "test", 8)]
    out = tmp_path / "meas"
    rep = run(
        _compose(
            [*TINY, "head=forest", "head.trees=25", "freeze=true", "frame_features=false",
             "measurements=true", f"classes=[{','.join(CLASSES)}]", "label_fraction=0.25",
             "context.frames=[5]",
             *_files("train", train), *_files("test", test), "logger=none", "smoothing.median=0",
             "smoothing.min_bout=0", f"output.dir={out}"]
        )
    )["report"]  # fmt: skip
    # per-frame speeds carry the toy's 0.5 mm point noise: about 0.94 is what they allow
    assert rep["raw"]["macro_f1"] >= 0.9, rep["raw"]
    model, meta = load_classifier(out / "classifier.pt")
    assert meta["measurements"] is True and model.encoder.measurements
    p = run(_compose(["mode=predict", f"checkpoint={out / 'classifier.pt'}",
                      f"tracks={test[0][0]}", f"output.dir={tmp_path / 'pred'}"]))  # fmt: skip
    df = pd.read_csv(p["predictions"])
    assert np.mean(df["label_raw"].to_numpy() == np.asarray(CLASSES)[test[0][2]]) >= 0.9


def _other_model_poses(poses: np.ndarray, body, Q: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The poses (T, 6) of `body` re-expressed for another model of the same animal, m' =
    Q (m - c) with c the model's centroid + shift (as `adjust-track body=auto`'s model: its own
    origin and axes): R' = R Q^T, t' = t + R (c + shift)... with the points unchanged."""
    from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix

    R = rodrigues_to_matrix(torch.tensor(poses[:, :3]))
    c = torch.tensor(np.asarray(body.points).mean(0) + shift)
    Qt = torch.tensor(Q)
    R2 = R @ Qt.T
    t2 = torch.tensor(poses[:, 3:]) + (R @ c[:, None])[..., 0]
    return np.concatenate((matrix_to_rodrigues(R2).numpy(), t2.numpy()), 1)


@pytest.mark.parametrize("what", ["axes", "origin"])
def test_read_tracks_pose_columns_of_another_body_model(tmp_path, caplog, what):
    """A track whose pose columns belong to another body model (e.g. adjust-track body=auto's:
    its own axes, or the same axes about another origin) is not read with this model's poses
    (silently wrong rigid points): a warning, and the pose fitted to the parts instead."""
    from deformnet.behavior.tracks import POSE_COLUMNS, pose_mismatch

    tracks, _, _ = _toy_session(tmp_path, "s", 0, T=60)
    body = default_mouse()
    own = read_tracks(tracks, body)
    assert own["pose"] == "columns"
    df = read_points3d_table(tracks)  # the pose columns are in the sidecar
    poses = df[list(POSE_COLUMNS)].to_numpy()
    if what == "axes":  # the principal axes of body=auto: y along the body, here rolled 90 deg
        Q, shift = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]), np.zeros(3)
    else:  # same axes, origin 15 mm away (the model's rms radius is 24 mm)
        Q, shift = np.eye(3), np.array([0.0, 15.0, 0.0])
    df[list(POSE_COLUMNS)] = _other_model_poses(poses, body, Q, shift)
    p = tmp_path / "other.csv"
    df.to_csv(p, index=False)
    pts = own["deformed"].astype(np.float64)
    bad = pose_mismatch(body, df[list(POSE_COLUMNS)].to_numpy(), pts, own["observed"])
    assert bad is not None and bad["frames"] == 60
    assert pose_mismatch(body, poses, pts, own["observed"]) is None
    with caplog.at_level("WARNING", logger="deformnet.behavior"):
        got = read_tracks(p, body)
    assert "other.csv: the pose columns do not belong to body model 'mouse'" in caplog.text
    assert got["pose"] == "fitted"
    # the pose fitted to the parts (0.5 mm noise per coordinate) gives the true rigid points:
    # about 0.2 mm per coordinate from the centroid's error (0.5 / sqrt(8)) and the rotation's
    d = got["rigid"] - own["rigid"]
    assert np.sqrt(np.mean(d**2)) < 0.4 and np.abs(d).max() < 1.5
    # with the other model's poses taken as this model's they would be far off
    wrong = transform_points(
        torch.tensor(df[list(POSE_COLUMNS)].to_numpy()),
        torch.tensor(np.asarray(body.points)).expand(60, -1, -1),
    ).numpy()
    assert np.abs(wrong - own["rigid"]).max() > 10.0
    # a part missing somewhere: no fit possible, an error naming the file, part and row
    df.loc[7, "left_ear_x"] = np.nan
    df.to_csv(p, index=False)
    with pytest.raises(ValueError, match=r"other.csv: the pose columns do not belong .*"
                       r"part 'left_ear' is missing in row 7"):  # fmt: skip
        read_tracks(p, body)


def test_pose_mismatch_keeps_deformed_tracks():
    """A track posed with its own model is not flagged though its parts deform (6 mm rms, more
    than the demo's simulated mouse) and some are unobserved."""
    from deformnet.behavior.tracks import pose_mismatch

    rng = np.random.default_rng(3)
    body = default_mouse()
    T = 200
    poses = np.concatenate((rng.normal(0, 1.0, (T, 3)), rng.normal(0, 100, (T, 3))), 1)
    m = torch.tensor(np.asarray(body.points)).expand(T, -1, -1)
    pts = transform_points(torch.tensor(poses), m).numpy() + rng.normal(0, 6 / 3**0.5, (T, 8, 3))
    obs = rng.random((T, 8)) > 0.3
    assert pose_mismatch(body, poses, pts, obs) is None
    # the same with the model turned by 90 degrees about its long axis in the poses: flagged
    Q = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    bad = pose_mismatch(body, _other_model_poses(poses, body, Q, np.zeros(3)), pts, obs)
    assert bad is not None and 80 < bad["angle_deg"] < 100


def test_the_default_recipe_needs_only_tracks_and_labels(tmp_path):
    """`deformnet-classify tracks=[...] labels=[...]` (the lab's command, nothing else): the
    forest head on the frame features and measurements, taught by the linear teacher; it labels
    a held-out session right. Unequal lists are an error naming both."""
    from deformnet.behavior.predict import run

    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = _toy_session(tmp_path, "test", 8)
    lab = [f"tracks=[{train[0][0]},{train[1][0]}]", f"labels=[{train[0][1]},{train[1][1]}]",
           f"classes=[{','.join(CLASSES)}]", f"data.test_tracks=[{test[0]}]",
           f"data.test_labels=[{test[1]}]", "logger=none"]  # fmt: skip
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("classify", overrides=[*lab, f"output.dir={tmp_path / 'out'}"])
        bad = hydra.compose("classify", overrides=[*lab[:1], f"labels=[{train[0][1]}]",
                                                   f"output.dir={tmp_path / 'bad'}"])  # fmt: skip
    rep = run(cfg)["report"]
    assert rep["split"] == "test" and rep["head_solver"] == "forest"
    assert rep["probe"]["pseudo_labels"]["teacher"] == "linear"
    assert rep["raw"]["macro_f1"] >= 0.95, rep["raw"]
    with pytest.raises(ValueError, match="tracks= has 2 files but labels= 1"):
        run(bad)
