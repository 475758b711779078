"""Deformable-body simulation of tet meshes in Warp (method.md §10, the Isaac Sim stand-in).

Newton's architecture: a static :class:`Model` built by a :class:`ModelBuilder`,
:class:`State` objects (positions, velocities), a :class:`Control` (kinematic plate poses)
and a solver, :class:`SolverVBDNeoHookean` (Vertex Block Descent: stable at any step), whose
``step(state_in, state_out, control, contacts, dt)`` is pure in its inputs. Scenarios are
TOML data (:func:`load_scene`); :func:`run_scene` steps one in memory. A scene may hold
several bodies (``[[bodies]]``); bodies touch each other, and so do the face-disconnected
pieces of one mesh. Files (mesh loading, USD, reports, renders) belong to the application
above this package, :mod:`holowarp.simulation`.
"""

from holowarp.sim.control import Control
from holowarp.sim.model import (
    GRAVITY,
    Body,
    Model,
    ModelBuilder,
    ModelError,
    Plate,
    lame_parameters,
)
from holowarp.sim.solver import PAPER_DT, PAPER_ITERATIONS, SolverVBDNeoHookean, StepPlan
from holowarp.sim.state import State
from holowarp.sim.scene import BodySpec, ContactSettings, Scene, SceneError, load_scene
from holowarp.sim.analysis import pieces_apart
from holowarp.sim.run import FPS, NonFiniteStateError, run_scene

__all__ = [
    "FPS",
    "GRAVITY",
    "PAPER_DT",
    "PAPER_ITERATIONS",
    "Body",
    "BodySpec",
    "ContactSettings",
    "Control",
    "Model",
    "ModelBuilder",
    "ModelError",
    "NonFiniteStateError",
    "Plate",
    "Scene",
    "SceneError",
    "SolverVBDNeoHookean",
    "StepPlan",
    "State",
    "lame_parameters",
    "load_scene",
    "pieces_apart",
    "run_scene",
]
