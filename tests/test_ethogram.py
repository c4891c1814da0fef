"""The behavior model where rules are not enough (deformnet.sim.ethogram)."""

from __future__ import annotations

import numpy as np

from deformnet.body import default_mouse
from deformnet.sim import SimConfig, simulate
from deformnet.sim.ethogram import ETHOGRAM, animal_config, annotate, simulate_ethogram

E = {c: i for i, c in enumerate(ETHOGRAM)}


def test_ethogram_reads_the_simulators_episodes_in_context():
    data, lab = simulate_ethogram(SimConfig(), 3000, 3)
    sim = np.asarray(data.behaviors)[data.labels]
    # the same animation: a walk is a walk or an approach, a rear is against a wall or free
    assert set(lab[sim == "walk"]) <= {E["walk"], E["approach"]}
    assert set(lab[sim == "rear"]) <= {E["rear_wall"], E["rear_free"]}
    assert set(lab[sim == "splint"]) <= {E["splint"], E["sniff"]}
    # an approach ends where a mechanism bout starts
    ends = np.flatnonzero((lab[:-1] == E["approach"]) & (lab[1:] != E["approach"]))
    assert ends.size and np.all(np.isin(sim[ends + 1], ["lever", "splint", "ball", "slider"]))
    assert {E["walk"], E["approach"], E["scan"]} <= set(lab.tolist())


def test_animals_differ_and_the_default_simulator_is_unchanged():
    a, b = animal_config(SimConfig(), 1), animal_config(SimConfig(), 2)
    assert a.body_scale != b.body_scale and a.walk.speed_mean != b.walk.speed_mean
    plain = simulate(SimConfig(), num_frames=300, seed=5, body=default_mouse())
    again = simulate(None, num_frames=300, seed=5)
    np.testing.assert_array_equal(plain.deformed, again.deformed)
    data, _ = simulate_ethogram(SimConfig(), 300, 5)
    assert not np.allclose(data.deformed, plain.deformed)  # another animal


def test_annotation_jitters_mislabels_and_misses_like_a_person():
    data, truth = simulate_ethogram(SimConfig(), 6000, 11)
    clean = annotate(truth, data.fps, np.random.default_rng(0), 0.0, 0.0, 0.0)
    noisy = annotate(truth, data.fps, np.random.default_rng(0))

    def frames(rows):
        y = np.full(len(truth), -1)
        for a, b, c in rows:
            assert b >= a
            y[a : b + 1] = c
        return y

    np.testing.assert_array_equal(frames(clean), truth)
    y = frames(noisy)
    assert np.all(y >= 0)  # every frame annotated once
    agree = float(np.mean(y == truth))
    assert 0.75 < agree < 0.98, agree
    missed = annotate(truth, data.fps, np.random.default_rng(0), 0.0, 0.0, 1.0)
    assert len(missed) < len(clean)  # every short bout missed: merged into the one before
    assert all(b - a + 1 >= data.fps for a, b, _ in missed[1:])
