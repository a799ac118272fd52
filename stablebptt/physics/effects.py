"""Which optional effects a scene can produce (``SceneEffects``): what scene analysis finds and every
later stage reads."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneEffects:
    """Which optional effects a scene can produce. False means: provably never."""

    contacts: bool
    joint_limits: bool
    tendon_limits: bool
    equality: bool
    friction_loss: bool
    springs: bool
    dampers: bool
    gravity_compensation: bool
    fluid: bool
    control_clamp: bool
    activation: bool
    tendons: bool
    sensors: bool

    @property
    def constraints(self) -> bool:
        """Whether the constraint solver can ever have rows."""
        return self.contacts or self.joint_limits or self.tendon_limits or self.equality or self.friction_loss

    @property
    def passive(self) -> bool:
        return self.springs or self.dampers or self.gravity_compensation or self.fluid
