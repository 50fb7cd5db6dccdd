"""The synthetic scene's script: the label vocabulary, the benchmark queries, the actions over normalized
time u in [0, 1] and the actors (people and the ball) that play them."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .parts import Pose, hand, lerp, person_transforms, smoothstep

BALL_RADIUS = 0.16

#: Ground-truth label vocabulary (index = value stored in ``labels.npy``).
LABELS: tuple[str, ...] = (
    "floor",
    "wall",
    "wooden box",
    "bench",
    "person standing",
    "person walking",
    "person jumping",
    "person waving",
    "person throwing the ball",
    "person catching the ball",
    "person holding the ball",
    "ball flying in the air",
    "ball in a hand",
)
LABEL_INDEX = {name: i for i, name in enumerate(LABELS)}

#: Benchmark queries: text -> the label names whose Gaussians are the answer.
QUERIES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("a person jumping", ("person jumping",)),
    ("a person waving", ("person waving",)),
    ("a person throwing the ball", ("person throwing the ball",)),
    ("a person catching the ball", ("person catching the ball",)),
    ("a person walking", ("person walking",)),
    ("a person holding the ball", ("person holding the ball",)),
    ("a ball flying in the air", ("ball flying in the air",)),
)

# ------------------------------------------------------------------------------------ script


@dataclass(frozen=True)
class Action:
    """One scripted action: ``actor`` performs ``label`` over normalized time [start, end)."""

    actor: str
    label: str
    start: float
    end: float


# Times are normalized to [0, 1]. Ball exchange: A throws to B, B throws a lob back to A.
_RELEASE_1, _ARRIVE_1 = 0.20, 0.33
_RELEASE_2, _ARRIVE_2 = 0.60, 0.84

SCRIPT: tuple[Action, ...] = (
    Action("A", "person holding the ball", 0.00, 0.12),
    Action("A", "person throwing the ball", 0.12, 0.25),
    Action("A", "person waving", 0.42, 0.60),
    Action("A", "person catching the ball", 0.76, 0.88),
    Action("A", "person holding the ball", 0.88, 1.01),
    Action("B", "person catching the ball", 0.25, 0.37),
    Action("B", "person holding the ball", 0.37, 0.52),
    Action("B", "person throwing the ball", 0.52, 0.64),
    Action("B", "person jumping", 0.70, 0.82),
    Action("C", "person walking", 0.00, 0.36),
    Action("C", "person jumping", 0.45, 0.58),
    Action("C", "person jumping", 0.76, 0.89),
)


class Actor:
    """A scripted person: a base stance, actions over time, and a walking path."""

    def __init__(self, name: str, position: np.ndarray, yaw: float, path_end: np.ndarray | None = None):
        self.name = name
        self.position = position
        self.yaw = yaw
        self.path_end = path_end
        self.actions = [a for a in SCRIPT if a.actor == name]

    def action_at(self, u: float) -> tuple[Action | None, float]:
        for a in self.actions:
            if a.start <= u < a.end:
                return a, (u - a.start) / (a.end - a.start)
        return None, 0.0

    def label_at(self, u: float) -> str:
        a, _ = self.action_at(u)
        return a.label if a else "person standing"

    def root_xy(self, u: float) -> tuple[np.ndarray, float]:
        if self.path_end is None:
            return self.position, self.yaw
        walk = next((a for a in self.actions if a.label == "person walking"), None)
        s = 0.0 if walk is None else min(max((u - walk.start) / (walk.end - walk.start), 0.0), 1.0)
        d = self.path_end - self.position
        heading = math.atan2(-d[0], d[1])
        pos = self.position + s * d
        turn = (self.yaw - heading + math.pi) % (2 * math.pi) - math.pi   # shortest way round
        yaw = heading if s < 1.0 else heading + turn * smoothstep((u - walk.end) / 0.06)
        return pos, yaw

    def pose(self, u: float) -> Pose:
        pos, yaw = self.root_xy(u)
        action, p = self.action_at(u)
        label = action.label if action else "person standing"
        z = 0.0
        arm_p, arm_a, elbow = [0.05, 0.05], [0.12, 0.12], [0.15, 0.15]
        leg_p, knee, lean = [0.0, 0.0], [0.03, 0.03], 0.0
        if label == "person walking":
            walk_len = float(np.linalg.norm(self.path_end - self.position)) if self.path_end is not None else 0
            phase = 2 * math.pi * (p * walk_len / 1.4)
            swing = math.sin(phase)
            leg_p = [0.45 * swing, -0.45 * swing]
            knee = [0.1 + 0.5 * max(0.0, -swing), 0.1 + 0.5 * max(0.0, swing)]
            arm_p = [-0.35 * swing, 0.35 * swing]
            elbow = [0.3, 0.3]
            z = 0.02 * abs(math.cos(phase))
        elif label == "person jumping":
            crouch = smoothstep(p / 0.2) * (1 - smoothstep((p - 0.2) / 0.08)) + \
                smoothstep((p - 0.8) / 0.1) * (1 - smoothstep((p - 0.9) / 0.1))
            air = min(max((p - 0.25) / 0.55, 0.0), 1.0)
            z = 0.5 * math.sin(math.pi * air) - 0.18 * crouch
            knee = [0.2 + 1.0 * crouch] * 2
            leg_p = [0.1 + 0.6 * crouch] * 2
            lean = 0.3 * crouch
            raise_ = math.sin(math.pi * air)
            arm_p = [0.3 + 2.5 * raise_] * 2
            arm_a = [0.2, 0.2]
            elbow = [0.2, 0.2]
        elif label == "person waving":
            up = smoothstep(p / 0.15) * (1 - smoothstep((p - 0.85) / 0.15))
            arm_a = [0.12 + 2.4 * up + 0.35 * up * math.sin(2 * math.pi * 3 * p), 0.12]
            elbow = [0.15 + 0.4 * up, 0.15]
            arm_p = [0.05 + 0.3 * up, 0.05]
        elif label == "person throwing the ball":
            if p < 0.45:
                s = smoothstep(p / 0.45)
                arm_p = [lerp(0.9, 3.7, s), 0.9 - 0.3 * s]
                elbow = [lerp(1.3, 1.4, s), 1.0]
            else:
                s = smoothstep((p - 0.45) / 0.55)
                arm_p = [lerp(3.7, 0.7, s), lerp(0.6, 0.1, s)]
                elbow = [lerp(1.4, 0.1, min(1.0, 2 * s)), 0.3]
                lean = 0.25 * math.sin(math.pi * s)
            arm_a = [0.15, 0.15]
            leg_p = [0.25, -0.2]
        elif label == "person catching the ball":
            reach = smoothstep(p / 0.35)
            arm_p = [lerp(0.05, 1.45, reach)] * 2
            arm_a = [0.22, 0.22]
            arrive = self._arrival_phase(action)
            pull = smoothstep((p - arrive) / 0.3) if p > arrive else 0.0
            elbow = [lerp(0.35, 1.3, pull)] * 2
            arm_p = [lerp(arm_p[0], 0.95, pull)] * 2
            knee = [0.15 + 0.2 * reach * (1 - pull)] * 2
        elif label == "person holding the ball":
            arm_p, arm_a, elbow = [0.95, 0.95], [0.22, 0.22], [1.3, 1.3]
        return Pose((float(pos[0]), float(pos[1]), z), yaw, tuple(arm_p), tuple(arm_a), tuple(elbow),
                     tuple(leg_p), tuple(knee), lean)

    @staticmethod
    def _arrival_phase(action: Action) -> float:
        for arrive in (_ARRIVE_1, _ARRIVE_2):
            if action.start <= arrive < action.end:
                return (arrive - action.start) / (action.end - action.start)
        return 0.5


def ball_state(u: float, actors: dict[str, Actor]) -> tuple[np.ndarray, str]:
    """Ball centre (3,) and its label at normalized time ``u``."""

    def held(actor: Actor, t: float) -> np.ndarray:
        tr = person_transforms(actor.pose(t))
        a, _ = actor.action_at(t)
        if a is not None and a.label == "person throwing the ball":
            return hand(tr, "r") + tr["torso"][0] @ np.array([0, 0.02, 0.08])
        mid = 0.5 * (hand(tr, "r") + hand(tr, "l"))
        return mid + tr["torso"][0] @ np.array([0, BALL_RADIUS * 0.9, 0.02])

    for (thrower, catcher, release, arrive, apex) in (("A", "B", _RELEASE_1, _ARRIVE_1, 0.5),
                                                      ("B", "A", _RELEASE_2, _ARRIVE_2, 0.9)):
        if release <= u < arrive:
            p0, p1 = held(actors[thrower], release - 1e-9), held(actors[catcher], arrive)
            s = (u - release) / (arrive - release)
            pos = (1 - s) * p0 + s * p1
            pos[2] += 4 * apex * s * (1 - s)
            return pos, "ball flying in the air"
    if u < _RELEASE_1:
        holder = "A"
    elif u < _RELEASE_2:
        holder = "B"
    else:
        holder = "A"
    return held(actors[holder], u), "ball in a hand"
