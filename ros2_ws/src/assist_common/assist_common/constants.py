"""Constants of the interface contract that more than one package uses (ARCHITECTURE.md)."""
from __future__ import annotations

# The paper's blending rule V = (u + a) / 2 if |a| > threshold else u ("TD3 implementation"): agent
# actions at or below this norm (m/s) are ignored. policy_node's default `blend_threshold`; the pilot
# station shows actions above it as "assistant acting".
BLEND_THRESHOLD_MPS = 0.25

BASE_FRAME = 'base_link'   # the body frame (REP-105, FLU)

# A velocity command (TwistStamped) is in base_link; an empty frame_id is read as base_link too.
ACCEPTED_CMD_FRAMES = ('', BASE_FRAME)
