"""Sensor register maps as data: the profile model and its loader."""

from gateway.profiles.loader import builtin_profiles, get_profile, load_profiles
from gateway.profiles.model import (
    Access,
    FloatOrderRegister,
    Limits,
    Point,
    PollGroup,
    Profile,
    Quirks,
    Ring,
    SerialSettings,
    Slope,
    Storage,
    Timing,
    WaitRule,
)

__all__ = [
    "Access",
    "FloatOrderRegister",
    "Limits",
    "Point",
    "PollGroup",
    "Profile",
    "Quirks",
    "Ring",
    "SerialSettings",
    "Slope",
    "Storage",
    "Timing",
    "WaitRule",
    "builtin_profiles",
    "get_profile",
    "load_profiles",
]
