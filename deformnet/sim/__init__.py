"""Deformable-mouse simulator (the paper's "Simulated Data", with behaviors and a lock box).

The rigid body model walks a smoothed random curve on the arena plane (heading along the path,
varying speed with stops, walls respected); the paws follow the paper's pace (right front + left
hind fixed to the ground while the other pair swings forward at twice the body speed, then the
pairs swap); the head triangle (nose tip, ears) rotates linearly back and forth in limited yaw,
pitch and roll intervals about the ears' midpoint. A Markov chain adds behaviors with their own
kinematics: scan (stopped, wide head sweeps), rear (pitched up about the hind paws, front paws
lifted), groom (front paws at the snout) and reaching the lock box's four mechanisms (the mouse
walks to the box, then brings its snout or a front paw to the mechanism).

Public API: `simulate`, `SimConfig`, `SimData`, `save_sim`, `load_sim`, `BEHAVIORS`,
`MECHANISMS`. NumPy/SciPy only (no torch or Lightning import).
"""

from deformnet.sim.config import BEHAVIORS, MECHANISMS, SimConfig
from deformnet.sim.dataset import SimData, load_sim, save_sim
from deformnet.sim.engine import simulate

__all__ = ["BEHAVIORS", "MECHANISMS", "SimConfig", "SimData", "load_sim", "save_sim", "simulate"]
