"""Fixed facts of the TABX world: unit catalogue, actions, zone types and default constants.

The unit table and the physics defaults come from the TABX paper (appendix A, table "Default
unit statistics") and the reference implementation's data files (MIT, Copyright (c) 2025 TABX;
see tabx/data/LICENSE-TABX). Nothing here is traced: these are Python values used to build
levels, never baked into a compiled step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# --- teams ---------------------------------------------------------------------------------
ALLY = 0
ENEMY = 1
NUM_TEAMS = 2

# --- actions -------------------------------------------------------------------------------
# World-frame moves, attack (heal for healers), two turns and idle; the reference's 8 actions.
UP, DOWN, LEFT, RIGHT, ATTACK, TURN_RIGHT, TURN_LEFT, IDLE = range(8)
NUM_ACTIONS = 8
ACTION_NAMES = ("up", "down", "left", "right", "attack", "turn_right", "turn_left", "idle")
# (dx, dy, dturn) per action: velocity direction and turn sign (+ = counter-clockwise).
ACTION_TABLE = (
    (0.0, 1.0, 0.0),
    (0.0, -1.0, 0.0),
    (-1.0, 0.0, 0.0),
    (1.0, 0.0, 0.0),
    (0.0, 0.0, 0.0),
    (0.0, 0.0, -1.0),
    (0.0, 0.0, 1.0),
    (0.0, 0.0, 0.0),
)

# --- zones ---------------------------------------------------------------------------------
ZONE_NONE, ZONE_LAVA, ZONE_BUSH, ZONE_SWAMP = 0, 1, 2, 3
ZONE_NAMES = ("none", "lava", "bush", "swamp")
ZONE_TYPE_BY_NAME = {name: i for i, name in enumerate(ZONE_NAMES)}
ZONE_CHAR = {"L": ZONE_LAVA, "B": ZONE_BUSH, "S": ZONE_SWAMP}

# --- reward modes --------------------------------------------------------------------------
REWARD_MEAN_OF_RATIOS = 0  # the paper's formula: mean over units of health / max health
REWARD_RATIO_OF_SUMS = 1  # the reference code: sum of health / sum of max health
REWARD_MODE_NAMES = ("mean_of_ratios", "ratio_of_sums")

# --- arena and physics defaults ------------------------------------------------------------
ARENA_WIDTH = 121.0
ARENA_HEIGHT = 78.0
SIGHT_ANGLE = math.pi / 2
TURN_RATE = math.pi / 6  # radians per second of simulated time; a turn action rotates rate*dt
BOUNDARY_DAMAGE_RATE = 0.1  # fraction of max health per second while touching the wall
DEFAULT_MAX_STEPS = 512
MAX_STEPS = 2**31 - 1  # episode limit: the step counter is int32


@dataclass(frozen=True)
class UnitSpec:
    """Default statistics of one unit type (paper table; reference `units.py`)."""

    name: str
    char: str
    health: float
    radius: float
    mass: float
    speed: float
    damage: float
    attack_range: float
    cooldown: float
    sight_angle: float = SIGHT_ANGLE
    space: int = 1  # grid cells per side occupied in the editor (mammoth: 2)

    @property
    def heals(self) -> bool:
        return self.damage < 0


# Order = the reference's 0-based `unit_ids` (ALL_UNIT_NAMES); scenario files use the names.
UNIT_SPECS: tuple[UnitSpec, ...] = (
    UnitSpec("farmer", "F", 60.0, 1.0, 1.0, 1.1, 14.0, 2.5, 2.5),
    UnitSpec("assassin", "S", 70.0, 1.0, 1.0, 1.4, 22.0, 2.5, 1.5),
    UnitSpec("theking", "K", 346.0, 1.47, 10.0, 1.2, 46.0, 3.2, 2.5),
    UnitSpec("mammoth", "M", 685.0, 4.25, 50.0, 1.2, 20.0, 3.0, 6.5, space=2),
    UnitSpec("archer", "A", 40.0, 1.0, 1.0, 1.0, 28.0, 27.0, 8.0),
    UnitSpec("cannon", "C", 100.0, 1.0, 5.2, 0.5, 80.0, 40.0, 10.0),
    UnitSpec("deadeye", "D", 40.0, 1.0, 1.0, 1.1, 25.0, 20.0, 8.0),
    UnitSpec("healer", "H", 25.0, 1.0, 1.0, 1.0, -7.0, 10.0, 2.0),
    UnitSpec("paladin", "P", 220.0, 1.32, 8.5, 1.2, -6.0, 7.5, 2.0),
)
NUM_UNIT_TYPES = len(UNIT_SPECS)
UNIT_NAMES = tuple(s.name for s in UNIT_SPECS)
UNIT_TYPE_BY_NAME = {s.name: i for i, s in enumerate(UNIT_SPECS)}
UNIT_TYPE_BY_CHAR = {s.char: i for i, s in enumerate(UNIT_SPECS)}
