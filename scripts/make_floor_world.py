"""Write config/worlds/floor.json from drivers.sim.floor_world (run after changing the generator).

    python scripts/make_floor_world.py
"""

from __future__ import annotations

from drivers.sim.floor_world import FLOOR_JSON, floor_world_json

if __name__ == "__main__":
    FLOOR_JSON.write_text(floor_world_json(), encoding="utf-8")
    print(f"wrote {FLOOR_JSON}")
