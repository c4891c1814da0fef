"""Lock-box events: contact detection with hysteresis on hand-built tracks, and adjust-events."""

from __future__ import annotations

import hydra
import numpy as np
import pandas as pd
import pytest

from adjust.events import contact_intervals, detect_events, first_operated, operations
from adjust.io import write_points3d
from adjust.settings import EventsConfig
from deformnet.paths import CONF_DIR

LEVER = np.array([100.0, 200.0, 20.0])
BALL = np.array([160.0, 200.0, 10.0])


def test_contact_intervals_hysteresis_and_min_duration():
    d = np.full(100, 30.0)
    d[10:20] = 5.0  # a clean contact
    # a contact whose distance jitters across the on threshold (8) but stays below off (12)
    d[40:60] = np.where(np.arange(20) % 2 == 0, 7.0, 10.0)
    d[80:82] = 5.0  # too short (2 frames)
    assert contact_intervals(d, on_mm=8, off_mm=12, min_frames=5) == [(10, 19), (40, 59)]
    # without hysteresis the jittering contact breaks into ten one-frame pieces, all too short
    assert contact_intervals(d, on_mm=8, off_mm=8, min_frames=1)[1:-1] == [
        (40 + 2 * i, 40 + 2 * i) for i in range(10)
    ]
    # merging bridges short gaps: two contacts 3 frames apart become one
    e = np.full(50, 30.0)
    e[5:15] = 2.0
    e[18:30] = 2.0
    assert contact_intervals(e, 8, 12, 5, merge_gap=4) == [(5, 29)]
    assert contact_intervals(e, 8, 12, 5, merge_gap=3) == [(5, 14), (18, 29)]
    # NaN (unknown) ends a contact; off < on is refused
    f = np.full(20, 2.0)
    f[10] = np.nan
    assert contact_intervals(f, 8, 12, 1) == [(0, 9), (11, 19)]
    with pytest.raises(ValueError, match="off_mm"):
        contact_intervals(f, 8, 4)


def _track(T: int = 300):
    """Three parts; the paw operates the lever twice (once jittering across the threshold) and
    the nose the ball once, in frames no camera saw."""
    parts = ["nose_tip", "left_front_paw", "tail_root"]
    rng = np.random.default_rng(0)
    P = np.zeros((T, 3, 3))
    P[:, 0] = [50.0, 50.0, 10.0]
    P[:, 1] = [60.0, 50.0, 0.0]
    P[:, 2] = [10.0, 10.0, 5.0]
    P += rng.normal(0, 0.3, P.shape)
    P[40:80, 1] = LEVER + [0.0, 0.0, 3.0]  # 3 mm: contact
    jit = np.where(np.arange(60) % 3 == 0, 6.0, 10.5)  # 6 / 10.5 mm: across on=8, below off=12
    P[150:210, 1] = LEVER + np.stack([jit, np.zeros(60), np.zeros(60)], -1)
    P[100:130, 0] = BALL + [1.0, 1.0, 0.0]
    ncams = np.full((T, 3), 2)
    ncams[100:130, 0] = 0  # the nose was seen by no camera during its contact
    sigma = np.where(ncams > 0, 0.5, 9.0)
    return parts, P, ncams, sigma


def test_detect_events_finds_exactly_the_planted_events():
    parts, P, ncams, sigma = _track()
    mechs = {"lever": LEVER, "ball": BALL}
    ev = detect_events(
        P, parts, mechs, ["nose_tip", "left_front_paw"], 8, 12, 5, 5, ncams, sigma, 5
    )
    got = [(e["start"], e["stop"], e["part"], e["mechanism"], e["inferred"]) for e in ev]
    assert got == [
        (40, 79, "left_front_paw", "lever", False),
        (100, 129, "nose_tip", "ball", True),
        (150, 209, "left_front_paw", "lever", False),
    ]
    assert ev[0]["min_distance_mm"] == pytest.approx(3.0, abs=1e-9)
    assert ev[2]["min_distance_mm"] == pytest.approx(6.0, abs=1e-9)
    assert first_operated(ev) == ["lever", "ball"]
    ops = operations(ev, 5)
    assert [(o["mechanism"], o["start"], o["stop"]) for o in ops] == [
        ("lever", 40, 79),
        ("ball", 100, 129),
        ("lever", 150, 209),
    ]
    # per-mechanism part restriction: the ball can only be operated with a paw
    ev2 = detect_events(
        P, parts, mechs, None, 8, 12, 5, 5, mechanism_parts={"ball": ["left_front_paw"]}
    )
    assert [e["mechanism"] for e in ev2] == ["lever", "lever"]
    with pytest.raises(ValueError, match="unknown part"):
        detect_events(P, parts, mechs, ["snout"])


def _cfg(overrides):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("events", overrides=overrides)


def test_the_switches_are_typed_and_their_yaml_defaults_are_the_dataclass_s():
    """conf/events.yaml's ``interpolate`` is `EventsConfig`'s default (the one copy in the
    code); absent, it keeps that default; a bad value names the setting."""
    cfg = _cfg([])
    assert cfg.interpolate == EventsConfig().interpolate
    assert EventsConfig.from_config(cfg) == EventsConfig() == EventsConfig.from_config({})
    assert EventsConfig.from_config(_cfg(["interpolate=true"])).interpolate
    with pytest.raises(ValueError, match="interpolate='often'"):
        EventsConfig.from_config({"interpolate": "often"})


def test_adjust_events_cli_writes_events_and_order(tmp_path):
    from adjust.apps.events import run

    parts, P, ncams, sigma = _track()
    T = len(P)
    tracks = write_points3d(
        tmp_path / "points3d.csv",
        parts,
        P,
        np.zeros((T, 3)),
        ncams,
        np.ones((T, 3)),
        extra={"{part}_sigma": sigma},
        fnum=np.arange(T) + 1000,
    )
    mech = "{lever: [100.0, 200.0, 20.0], ball: [160.0, 200.0, 10.0]}"
    res = run(
        _cfg(
            [
                f"tracks={tracks}",
                f"mechanisms={mech}",
                "parts=[nose_tip,left_front_paw]",
                "contact.on_mm=8",
                "contact.off_mm=12",
                "contact.merge_gap=5",
                f"output.dir={tmp_path / 'ev'}",
            ]
        )
    )
    assert res["order"] == ["lever", "ball"]
    assert res["events"] == 3 and res["inferred_events"] == 1
    df = pd.read_csv(tmp_path / "ev" / "events.csv")
    assert df[["start", "stop"]].values.tolist() == [[1040, 1079], [1100, 1129], [1150, 1209]]
    assert df["inferred"].tolist() == [False, True, False]
    assert res["first_operated"] == {"lever": 1040, "ball": 1100}
    # no mechanism positions at all: a clear error
    with pytest.raises(ValueError, match="mechanisms"):
        run(_cfg([f"tracks={tracks}", f"output.dir={tmp_path / 'ev2'}"]))


def test_mechanisms_from_simulated_scene_calibration(tmp_path):
    """adjust-simulate writes the mechanisms into the calibration's metadata; adjust-events reads
    them from there."""
    from adjust.apps.events import mechanism_positions
    from adjust.apps.simulate import run as simulate

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("scene", overrides=[f"output.dir={tmp_path}", "num_frames=40"])
    res = simulate(cfg)
    mech = mechanism_positions(_cfg(["tracks=x", f"calibration={res['calibration']}"]))
    assert list(mech) == ["lever", "splint", "ball", "slider"]
    from deformnet.sim import simulate as sim

    data = sim(None, num_frames=5, seed=0)
    np.testing.assert_allclose(np.array(list(mech.values())), data.mechanism_positions)


def test_adjust_events_durations_in_seconds_at_any_frame_rate(tmp_path):
    """With fps= the contact durations can be set in seconds (contact.min_seconds,
    contact.merge_gap_seconds) and the tables get start_s / stop_s: the same track recorded at
    30 and at 90 fps (each frame three times) gives the same events in seconds, to a frame at
    30 fps. Seconds without a frame rate are an error."""
    from adjust.apps.events import run

    parts, P, ncams, sigma = _track()
    mech = "{lever: [100.0, 200.0, 20.0], ball: [160.0, 200.0, 10.0]}"
    res = {}
    for fps, rep in ((30, 1), (90, 3)):
        T = len(P) * rep
        sig = {"{part}_sigma": np.repeat(sigma, rep, 0)}
        tracks = write_points3d(
            tmp_path / f"p{fps}.csv", parts, np.repeat(P, rep, 0), np.zeros((T, 3)),
            np.repeat(ncams, rep, 0), np.ones((T, 3)), extra=sig,
        )  # fmt: skip
        ov = [f"tracks={tracks}", f"mechanisms={mech}", "parts=[nose_tip,left_front_paw]",
              "contact.on_mm=8", "contact.off_mm=12", f"fps={fps}", "contact.min_seconds=0.5",
              "contact.merge_gap_seconds=0.2", f"output.dir={tmp_path / str(fps)}"]  # fmt: skip
        res[fps] = run(_cfg(ov))
        assert res[fps]["fps"] == fps
        assert res[fps]["contact"]["min_frames"] == 15 * rep
        assert res[fps]["contact"]["merge_gap"] == 6 * rep
    a, b = (pd.read_csv(tmp_path / str(f) / "events.csv") for f in (30, 90))
    assert len(a) == len(b) == 3 and (a["mechanism"] == b["mechanism"]).all()
    assert (
        np.abs(a[["start_s", "stop_s"]].to_numpy() - b[["start_s", "stop_s"]].to_numpy()).max()
        <= 1 / 30 + 1e-9
    )
    np.testing.assert_allclose(a["start_s"], a["start"] / 30)
    ops = pd.read_csv(tmp_path / "90" / "operations.csv")
    assert list(ops.columns) == ["mechanism", "start", "stop", "start_s", "stop_s", "parts"]
    with pytest.raises(ValueError, match=r"contact.min_seconds=0.5 needs the frame rate: set fps="):
        run(_cfg([f"tracks={tmp_path / 'p30.csv'}", f"mechanisms={mech}",
                  "contact.min_seconds=0.5", f"output.dir={tmp_path / 'bad'}"]))  # fmt: skip
    # the frame rate from the calibration's [metadata] fps, as adjust-export reads it
    calib = tmp_path / "calibration.toml"
    calib.write_text(
        "[metadata]\nfps = 90.0\n\n[metadata.mechanisms]\n"
        "lever = [100.0, 200.0, 20.0]\nball = [160.0, 200.0, 10.0]\n"
    )
    got = run(_cfg([f"tracks={tmp_path / 'p90.csv'}", f"calibration={calib}",
                    "parts=[nose_tip,left_front_paw]", "contact.on_mm=8", "contact.off_mm=12",
                    "contact.min_seconds=0.5", "contact.merge_gap_seconds=0.2",
                    f"output.dir={tmp_path / 'meta'}"]))  # fmt: skip
    assert got["fps"] == 90.0 and got["contact"]["min_frames"] == 45
    assert pd.read_csv(tmp_path / "meta" / "events.csv").equals(b)
