"""Which configured method and scenario plays which part of the study.

The study's findings speak of voxel methods by what they are (fixed cubes of 0.25 m, PAD-scaled
cubes shifted to the centre of gravity, …) and of surveys by sensor (ALS, ULS). A run names its
methods and scenarios freely, so the part each one plays is read from its configuration, never
from its name:

* a method's part comes from its ``kind`` and parameters: ``{kind: fixed, voxel_size: s}`` plays
  the study's fixed method of cell size ``s`` (0.25, 0.10, 0.05 or 0.02 m), and
  ``{kind: scaled, a0: 0.25, alpha: 0.5, shift: none | random | cog}`` the study's scaled
  method with that shift. Other methods play no part; they are compared with the references
  all the same.
* a scenario's part is its ``platform`` key (``als`` or ``uls``) when it has one, else the part
  of its ``scanner``: the study flew the RIEGL VQ-780i as ALS and the miniVUX-1UAV as ULS
  (:data:`STUDY_SCANNERS`). A scenario with another scanner plays no part.

:meth:`StudyRoles.from_config` builds the roles from a workflow configuration's ``methods`` and
``scenarios`` blocks; :meth:`StudyRoles.method` and :meth:`StudyRoles.scenarios_of` answer the
findings' questions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from vlsforest.errors import ConfigError

__all__ = ["STUDY_FIXED_SIZES", "STUDY_SHIFTS", "STUDY_SCANNERS", "PLATFORMS", "MethodRole", "StudyRoles",
           "study_label"]

#: the study's fixed cell sizes (m), largest first (Table 2)
STUDY_FIXED_SIZES = (0.25, 0.10, 0.05, 0.02)
#: the study's shifts of the scaled cubes (Table 2)
STUDY_SHIFTS = ("none", "random", "cog")
#: the study's scaling parameters: base cell a0 (m) and exponent alpha (§ Methods 4)
STUDY_SCALING = {"a0": 0.25, "alpha": 0.5}
#: the study's two surveys
PLATFORMS = ("als", "uls")
#: scanner presets the study flew, by the survey they flew in
STUDY_SCANNERS = {"riegl_vq780i": "als", "riegl_minivux1uav": "uls", "riegl_minivux1uav_helios1": "uls"}


def study_label(kind: str, part) -> str:
    """How the findings name one of the study's methods: ``("fixed", 0.25)`` → ``"0.25 m fixed"``,
    ``("scaled", "cog")`` → ``"scaled + CoG shift"``."""
    if kind == "fixed":
        return f"{float(part):.2f} m fixed"
    return {"none": "scaled", "random": "scaled + random shift", "cog": "scaled + CoG shift"}.get(part, "scaled")


def _close(a, b) -> bool:
    return a is not None and math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)


@dataclass(frozen=True)
class MethodRole:
    """The study's part a configured method plays.

    Attributes
    ----------
    name : str
        The method's name in the configuration.
    kind : str
        ``"fixed"`` or ``"scaled"`` (the study's), or the configured kind of another method.
    size : float or None
        Fixed: the cell size (m); scaled: the base cell ``a0`` (m).
    shift : str or None
        Scaled: ``"none"``, ``"random"`` or ``"cog"``.
    study : bool
        Whether it is one of the study's seven methods (Table 2).
    """

    name: str
    kind: str
    size: float | None = None
    shift: str | None = None
    study: bool = False

    @property
    def label(self) -> str:
        """How the findings name the part, e.g. ``"0.25 m fixed"`` or ``"scaled + CoG shift"``."""
        if self.kind == "fixed" and self.size is not None:
            return study_label("fixed", self.size)
        if self.kind == "scaled":
            return study_label("scaled", self.shift or "none")
        return self.name


@dataclass(frozen=True)
class StudyRoles:
    """The parts of a run's methods and scenarios in the study.

    Attributes
    ----------
    methods : tuple of MethodRole
        Every configured method, in configuration order.
    platforms : dict of str to str
        Scenario name → ``"als"`` or ``"uls"`` for the scenarios that play one of the study's
        surveys, in configuration order.
    scenario_names : tuple of str
        Every configured scenario, in configuration order.
    """

    methods: tuple[MethodRole, ...] = ()
    platforms: Mapping[str, str] = field(default_factory=dict)
    scenario_names: tuple[str, ...] = ()

    @classmethod
    def from_config(cls, methods: Mapping | None, scenarios: Mapping | None) -> StudyRoles:
        """Roles from a configuration's ``methods`` and ``scenarios`` blocks.

        Parameters
        ----------
        methods : mapping
            Method name → its block (``kind`` and parameters).
        scenarios : mapping
            Scenario name → its block (``scanner``, optional ``platform``).

        Returns
        -------
        StudyRoles

        Raises
        ------
        ConfigError
            A block that is not a mapping, a method without ``kind`` or a ``platform`` that is
            not ``als`` or ``uls``.
        """
        roles = []
        for name, block in (methods or {}).items():
            if not isinstance(block, Mapping) or "kind" not in block:
                raise ConfigError(f"methods.{name}: must be a mapping with a 'kind'")
            kind = str(block["kind"])
            if kind == "fixed":
                size = block.get("voxel_size")
                study = any(_close(size, s) for s in STUDY_FIXED_SIZES)
                roles.append(MethodRole(str(name), kind, None if size is None else float(size), None, study))
            elif kind == "scaled":
                a0 = block.get("a0", STUDY_SCALING["a0"])
                shift = str(block.get("shift", "none"))
                study = (_close(a0, STUDY_SCALING["a0"]) and _close(block.get("alpha", STUDY_SCALING["alpha"]),
                                                                     STUDY_SCALING["alpha"])
                         and shift in STUDY_SHIFTS)
                roles.append(MethodRole(str(name), kind, float(a0), shift, study))
            else:
                roles.append(MethodRole(str(name), kind))
        platforms = {}
        for name, block in (scenarios or {}).items():
            if not isinstance(block, Mapping):
                raise ConfigError(f"scenarios.{name}: must be a mapping")
            plat = block.get("platform")
            if plat is not None and plat not in PLATFORMS:
                raise ConfigError(f"scenarios.{name}.platform: must be one of {', '.join(PLATFORMS)}, got {plat!r}")
            plat = plat or STUDY_SCANNERS.get(str(block.get("scanner", "")))
            if plat:
                platforms[str(name)] = plat
        return cls(tuple(roles), platforms, tuple(str(s) for s in (scenarios or {})))

    @property
    def method_names(self) -> tuple[str, ...]:
        """The configured methods' names, in configuration order."""
        return tuple(r.name for r in self.methods)

    def method(self, kind: str, size: float | None = None, shift: str | None = None) -> str | None:
        """The first configured method that plays the study's method ``kind`` (``size``/``shift``).

        Parameters
        ----------
        kind : {"fixed", "scaled"}
        size : float, optional
            Fixed: the cell size (m).
        shift : str, optional
            Scaled: ``"none"``, ``"random"`` or ``"cog"``.

        Returns
        -------
        str or None
            Its name, or None when no configured method plays it.
        """
        for r in self.methods:
            if not r.study or r.kind != kind:
                continue
            if kind == "fixed" and _close(r.size, size):
                return r.name
            if kind == "scaled" and r.shift == (shift or "none"):
                return r.name
        return None

    def role(self, name: str) -> MethodRole | None:
        """The role of method ``name``, or None for a name not in the configuration."""
        for r in self.methods:
            if r.name == name:
                return r
        return None

    def fixed_methods(self) -> list[MethodRole]:
        """The study's fixed methods that are configured, largest cell first."""
        return sorted((r for r in self.methods if r.study and r.kind == "fixed"), key=lambda r: -r.size)

    def scenarios_of(self, platform: str) -> list[str]:
        """The scenarios that play the study's ``platform`` survey (``"als"`` or ``"uls"``)."""
        return [s for s, p in self.platforms.items() if p == platform]
