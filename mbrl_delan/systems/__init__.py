"""MuJoCo systems: loading, joint layout, actuation, torch position arithmetic."""

from mbrl_delan.systems.system import JointLayout, State, System, asset_path, load_system

__all__ = ["JointLayout", "State", "System", "asset_path", "load_system"]
