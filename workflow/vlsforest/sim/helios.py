"""HELIOS++ XML export: a scene and a survey as files that HELIOS++ 1.0.8 and 2.x run.

One folder holds what HELIOS++ reads (written whole or not at all,
:func:`vlsforest.io.atomic.atomic_dir`):

``scene.xml`` with ``part_{id}.obj`` / ``part_{id}.vox``
    The scene (:func:`export_scene`, :func:`write_scene_xml`): planes and meshes as OBJ, voxels
    in full cells as AMAPVox ``.vox`` (``fixed`` mode), cubes scaled about their cell centres as
    ``.vox`` in ``scaled`` mode, other cubes as OBJ cubes. Part ids are our object ids.
``survey.xml``
    ``<survey name scene platform scanner seed>`` with the survey's ``<FWFSettings>`` and one
    ``<leg>`` per waypoint, each with ``<platformSettings>`` and ``<scannerSettings>``
    (:func:`export_survey`, :func:`survey_documents`).
``scanner.xml``
    One ``<scanner>`` entry: the survey's scanner as it runs (preset and overrides).
``platform.xml``
    One ``<platform>``: ``linearpath`` for a linear survey, ``static`` for TLS positions.

Run it from inside the folder (both versions resolve relative paths from the working
directory)::

    cd OUT && helios survey.xml --output helios_output/

HELIOS++ 2.x also looks relative paths up in its ``--assets`` folders::

    helios OUT/survey.xml --assets OUT/

How the survey is written
-------------------------
*Legs.* A HELIOS++ leg is a waypoint: the platform flies from it to the next one with the
leg's speed (``movePerSec_m``) and scanner settings (``active``). Survey leg i becomes the
waypoint at its start, with its speed and ``active``; where a leg does not start where the
previous one ended, an inactive waypoint at the previous end (flown at the leg's speed, as the
simulator times the transit) comes first; the last leg's end closes the list as an inactive
waypoint. ``onGround`` is false: the coordinates are absolute. A linear leg must not be
vertical (HELIOS++ turns the platform to face the next waypoint horizontally).

*Frames.* HELIOS++'s beam is ``mount · head · emitter · deflector · (0, 1, 0)`` with
right-handed rotations; its deflectors turn the beam about x. The linear platform faces its
next waypoint, level, as the simulator's; the scanner mount ``rot x −90°, then rot z −90°``
maps a deflection angle a to ``(sin a, 0, −cos a)`` in the platform frame, the simulator's
across-track beam (positive a to the right of the track). A TLS head turns about
``(0, 0, −1)``, so a positive head angle is the simulator's clockwise azimuth; the scan's
heading is added to the head's start and stop angles; the scanner's ``beamOrigin`` is tilted
about x by the centre of the vertical field of view, so a mirror sweeping ±half of it covers
``tls_v_fov_deg``; a tilt common to every position goes into the static platform's mount.

*Scanner.* Deflector ``polygon`` → optics ``rotating`` (``scanAngleMax_deg`` the mirror's
half sweep, ``scanAngleEffectiveMax_deg`` the emitting limit); ``rotating`` (a 360° mirror) →
``rotating`` with ``scanAngleMax_deg`` 180; ``oscillating`` → ``oscillating`` with half the
line frequency (HELIOS++ counts a period, there and back, as one line); ``conic`` →
``conic`` with ``scanFreqMax_Hz`` the survey's frequency (HELIOS++ turns the cone at the
device's maximum); ``tls`` → ``rotating`` whose line frequency gives the vertical step
(``tls_v_step_deg · PRF / vertical span``) and a head turning ``tls_h_step_deg`` per line.
``beamDivergence_rad`` is the 1/e² half angle (``beam_divergence_mrad``, the same convention);
``accuracy_m`` ← ``range_noise_m``, ``rangeMin_m`` ← ``range_min_m``, ``maxNOR`` ←
``max_returns``, ``receivedEnergyMin_W`` (2.x; 1.0.8 uses a fixed 0.001) ← ``min_energy`` or
0.001; the energy-model constants by name. Without ``atmosphere`` the visibility is written
as :data:`NO_ATMOSPHERE_VISIBILITY_KM` (HELIOS++ always attenuates; at 10⁹ km its extinction
is below 10⁻¹³ per metre). ``FWFSettings`` carry ``bin_size_ns``, ``window_size_ns`` and
``beam_sample_quality``. The survey's ``output`` section and ``beam_exit_diameter_m`` are not
simulation settings and are not written.

Approximations
--------------
What HELIOS++ cannot run is refused with :class:`~vlsforest.errors.ConfigError` naming the
key, unless approximations are allowed; then the export writes the downgrade listed here,
reports it (:class:`Approximation`) and states it in an XML comment:

- an elliptical beam (major ≠ minor): a circular beam of the geometric mean (the same
  footprint area);
- detector switches other than those of ``helios_v1`` (the default ``physical`` detector
  included): HELIOS++'s own detector;
- a ``min_energy`` other than 0.001: ``receivedEnergyMin_W``, read by HELIOS++ 2.x only;
- trajectory noise: none (HELIOS++'s platform noise is another model);
- a PRF, line frequency or wavelength that is not an integer: the nearest integer (HELIOS++
  reads them as integers, line frequencies only in 1.0.8);
- TLS positions with different tilts, or a tilt with a heading: the first position's tilt in
  the mount, the headings as head angles inside it.

Known differences of HELIOS++'s own scan model (not approximations of the export): its
oscillating mirror slows down at the turns, its TLS head turns continuously during a line,
and its 2.x energy model is not 1.0.8's (which ``detector: {mode: helios_v1}`` reproduces).
The scene's reflectances are stated in XML comments, not as HELIOS++ materials: HELIOS++ 1.0.8
gives every primitive without a spectrum 50 %.
"""

from __future__ import annotations

import dataclasses
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import yaml

from vlsforest.domain.cubes import cube_triangles
from vlsforest.errors import ConfigError
from vlsforest.sim import DetectorOptions, ScannerSettings, Survey, load_survey
from vlsforest.sim.deflector import tls_grid
from vlsforest.sim.scanner import input_key

__all__ = ["Approximation", "NO_ATMOSPHERE_VISIBILITY_KM", "PLATFORM_FILE", "SCANNER_FILE", "SCENE_FILE",
           "SURVEY_FILE", "SurveyXml", "export_scene", "export_survey", "survey_documents", "write_scene_xml"]

SCENE_FILE = "scene.xml"
SURVEY_FILE = "survey.xml"
SCANNER_FILE = "scanner.xml"
PLATFORM_FILE = "platform.xml"

#: the visibility written for a scanner without ``atmosphere`` (HELIOS++ always attenuates)
NO_ATMOSPHERE_VISIBILITY_KM = 1.0e9

#: HELIOS++ 1.0.8's fixed detection threshold (the simulator's helios rule uses it for min_energy 0)
_HELIOS_THRESHOLD = 0.001
#: HELIOS++'s default oscillating-mirror scan product (angle in degrees × frequency in Hz)
_SCAN_PRODUCT = 1_000_000
_XML_HEAD = '<?xml version="1.0" encoding="UTF-8"?>\n'


# ----------------------------------------------------------------------------------- scenes


def write_scene_xml(scene_yaml, folder, scene_id: str = "vlsforest_scene") -> Path:
    """Write a SCENE.yaml as a HELIOS++ scene into an existing folder.

    The scene is read by the simulator's own reader (:meth:`vlsforest.sim.Scene.from_yaml`),
    so every part it accepts is exported, and a bad part fails before anything is written:
    planes and meshes as OBJ, voxels in full cells as a ``.vox`` (``fixed`` mode), cubes
    scaled about their cell centres as a ``.vox`` (``scaled`` mode: PAD rescaled to one
    ``#max_pad`` per file so the cube sides are exactly ours), other cubes (shifted) as OBJ
    cubes (HELIOS++ cannot read per-cube offsets; its own ``randomShift`` draws other numbers).
    The reflectance and classification of each part are stated in an XML comment.

    Parameters
    ----------
    scene_yaml : path
    folder : path
        Folder for ``scene.xml`` and its parts (``part_{id}.obj`` / ``part_{id}.vox``); each
        file is written atomically, the folder as a whole is not (see :func:`export_scene`).
    scene_id : str
        The XML scene id.

    Returns
    -------
    Path
        ``folder/scene.xml``. Part ids are our object ids, so HELIOS++'s ``hitObjectId`` matches
        our ``object_id``.
    """
    from vlsforest.io.atomic import write_text
    from vlsforest.io.mesh import TriangleMesh, write_mesh
    from vlsforest.io.vox import make_vox, write_vox
    from vlsforest.sim.scene import Scene

    scene_yaml = Path(scene_yaml)
    tmp = Path(folder)
    scene = Scene.from_yaml(scene_yaml)
    doc = yaml.safe_load(scene_yaml.read_text())
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<document>",
             f"  <scene id={quoteattr(scene_id)} name={quoteattr(str(doc.get('name') or scene_id))}>"]

    def material(part):
        return (f"      <!-- reflectance {part.material.reflectance} at the scanner wavelength; "
                f"classification {part.classification} -->")

    def obj_filter(fname):
        return ['      <filter type="objloader">',
                f'        <param type="string" key="filepath" value={quoteattr(fname)} />', "      </filter>"]

    def vox_filter(fname, mode):
        out = ['      <filter type="detailedVoxels">',
               f'        <param type="string" key="filepath" value={quoteattr(fname)} />',
               f'        <param type="string" key="intersectionMode" value="{mode}" />']
        if mode == "scaled":
            out.append('        <param type="double" key="intersectionArgument" value="0.5" />')
        return out + ["      </filter>"]

    for g in scene.part_geometries():
        part = g["part"]
        pid = part.object_id
        lines.append(f'    <part id="{pid}">')
        if g["kind"] == "plane":
            x0, y0, x1, y1 = g["extent"]
            z = float(g["z"])
            v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
            fname = f"part_{pid}.obj"
            write_mesh(tmp / fname, TriangleMesh(v, np.array([[0, 1, 2], [0, 2, 3]])))
            lines += obj_filter(fname)
        elif g["kind"] == "mesh":
            fname = f"part_{pid}.obj"
            write_mesh(tmp / fname, TriangleMesh(g["vertices"], g["faces"]))
            lines += obj_filter(fname)
        else:
            ijk, size, half, centre = g["ijk"], g["size"], g["half"], g["centre"]
            origin = np.asarray(g["origin"], dtype=np.float64)
            centred = centre is None or np.allclose(centre, origin + (ijk + 0.5) * size)
            if half is None or centred:
                lo = ijk.min(axis=0)
                cols, pad_max, mode = {}, None, "fixed"
                if half is not None:  # HELIOS++ scaled side size·(PAD/pad_max)^0.5 = 2·half
                    cols, pad_max, mode = {"PadBVTotal": (2.0 * half / size) ** 2}, 1.0, "scaled"
                fname = f"part_{pid}.vox"
                write_vox(tmp / fname, make_vox(ijk - lo, size, origin + lo * size, cols, max_pad=pad_max,
                                                header={"type": "TLS", "build-version": "1.4.3"}))
                lines += vox_filter(fname, mode)
            else:
                v, f = cube_triangles(centre, half)
                fname = f"part_{pid}.obj"
                write_mesh(tmp / fname, TriangleMesh(v, f))
                lines += obj_filter(fname)
        lines += [material(part), "    </part>"]
    lines += ["  </scene>", "</document>", ""]
    write_text(tmp / SCENE_FILE, "\n".join(lines))
    return tmp / SCENE_FILE


def export_scene(scene_yaml, out_dir, scene_id: str = "vlsforest_scene") -> Path:
    """Write a SCENE.yaml as a HELIOS++ scene folder, whole or not at all.

    Parameters
    ----------
    scene_yaml : path
    out_dir : path
        Folder for ``scene.xml`` and its parts (see :func:`write_scene_xml`); it appears whole
        or not at all (:func:`vlsforest.io.atomic.atomic_dir`).
    scene_id : str
        The XML scene id.

    Returns
    -------
    Path
        ``out_dir/scene.xml``.
    """
    from vlsforest.io.atomic import atomic_dir

    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        write_scene_xml(scene_yaml, tmp, scene_id)
    return out_dir / SCENE_FILE


# ---------------------------------------------------------------------------------- surveys


@dataclass(frozen=True)
class Approximation:
    """A survey setting HELIOS++ cannot run, and what the export writes in its place.

    Attributes
    ----------
    key : str
        The survey key (e.g. ``scanner.beam_divergence_mrad``).
    problem : str
        What HELIOS++ lacks.
    written : str
        What the XML holds instead.
    """

    key: str
    problem: str
    written: str

    def __str__(self) -> str:
        return f"{self.key}: {self.problem}; written as {self.written}"


@dataclass(frozen=True)
class SurveyXml:
    """The XML documents of a survey (text of each file) and the approximations made.

    Attributes
    ----------
    survey, scanner, platform : str
        The contents of ``survey.xml``, ``scanner.xml`` and ``platform.xml``.
    approximations : tuple of Approximation
        Empty when the files run the survey as the simulator does.
    """

    survey: str
    scanner: str
    platform: str
    approximations: tuple


def _num(v) -> str:
    """A number as HELIOS++ parses it: an integral value without a decimal point (so that
    integer attributes read), any other value in the shortest form that reads back exactly."""
    v = float(v)
    if not math.isfinite(v):
        raise ConfigError(f"cannot write the non-finite value {v} to HELIOS++ XML")
    if v.is_integer() and abs(v) < 1e15:
        return str(int(v))
    return repr(v)


def _is_integer(v: float) -> bool:
    return abs(v - round(v)) <= 1e-9 * max(1.0, abs(v))


def _ident(name: str) -> str:
    """An asset id HELIOS++ can address (``file.xml#id``): letters, digits, ``_ . -`` only."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", str(name)) or "vlsforest"


def _comment(text: str) -> ET.Element:
    return ET.Comment(" " + text.replace("--", "- -") + " ")


def _document(element: ET.Element, comments=()) -> str:
    """``<?xml …?><document>`` with comments and one asset; the declaration is followed directly
    by ``<document>`` (HELIOS++ 1.0.8 takes the declaration's next sibling as the document)."""
    root = ET.Element("document")
    for c in comments:
        root.append(_comment(c))
    root.append(element)
    ET.indent(root, space="  ")
    return _XML_HEAD + ET.tostring(root, encoding="unicode") + "\n"


def _element(tag: str, attrs: dict, parent: ET.Element | None = None) -> ET.Element:
    text = {k: (v if isinstance(v, str) else ("true" if v is True else "false") if isinstance(v, bool) else _num(v))
            for k, v in attrs.items()}
    return ET.Element(tag, text) if parent is None else ET.SubElement(parent, tag, text)


class _Collector:
    """The approximations of one export, in the order met."""

    def __init__(self):
        self.items: list[Approximation] = []

    def add(self, key, problem, written):
        self.items.append(Approximation(key, problem, written))

    def integer(self, value: float, key: str, what: str, versions: str = "HELIOS++") -> int:
        """``value`` as the integer HELIOS++ reads; a non-integral value is rounded and noted."""
        n = int(round(float(value)))
        if not _is_integer(float(value)):
            self.add(key, f"{versions} reads the {what} as an integer, the survey's is {float(value):g}",
                     f"{max(n, 1)}")
        return max(n, 1)


@dataclass(frozen=True)
class _Optics:
    """The HELIOS++ deflector of a scanner and the per-leg values that drive it."""

    optics: str
    angle_max_deg: float
    angle_effective_deg: float | None
    scan_angle_deg: float
    scan_freq_hz: float
    head_speed_deg: float = 0.0
    head_step_deg: float = 0.0
    emitter_tilt_deg: float = 0.0
    head_axis_z: float = 1.0


def _optics(s: ScannerSettings, prf: int, col: _Collector) -> _Optics:
    """Map a scanner's deflector onto a HELIOS++ one (see the module docstring)."""
    d = s.deflector
    key = _key("deflector", "scan_freq_hz")
    line = "line frequency"
    if d.kind == "polygon":
        f = col.integer(d.scan_freq_hz, key, line, "HELIOS++ 1.0.8")
        return _Optics("rotating", d.max_scan_angle_deg, d.effective_max_scan_angle_deg, d.scan_angle_deg, f)
    if d.kind == "rotating":
        f = col.integer(d.scan_freq_hz, key, line, "HELIOS++ 1.0.8")
        return _Optics("rotating", 180.0, d.effective_max_scan_angle_deg, d.scan_angle_deg, f)
    if d.kind == "oscillating":
        f = col.integer(d.scan_freq_hz / 2.0, key, "mirror period frequency (half the line frequency)",
                        "HELIOS++ 1.0.8")
        return _Optics("oscillating", d.max_scan_angle_deg, None, d.scan_angle_deg, f)
    if d.kind == "conic":
        f = col.integer(d.scan_freq_hz, key, "rotation frequency", "HELIOS++ 1.0.8")
        return _Optics("conic", d.max_scan_angle_deg, None, d.scan_angle_deg, f)
    # tls: a vertical mirror line per azimuth step, the head turning one step per line
    g = s.tls
    v0, v1 = g.v_fov_deg
    half = 0.5 * (v1 - v0)
    v_step = input_key("tls", "v_step_deg")
    f = col.integer(g.v_step_deg * prf / (v1 - v0), f"scanner.{v_step}",
                    f"line frequency ({v_step} · PRF / vertical span)", "HELIOS++ 1.0.8")
    step = g.h_step_deg
    return _Optics("rotating", half, half, half, f, head_speed_deg=step * f, head_step_deg=step,
                   emitter_tilt_deg=0.5 * (v0 + v1), head_axis_z=-1.0)


def _key(part: str, name: str) -> str:
    """The survey key of a scanner setting (``scanner.<flat key>``) in messages."""
    return f"scanner.{input_key(part, name)}"


def _scanner_approximations(s: ScannerSettings, survey: Survey, col: _Collector) -> dict:
    """The scanner values that are not one-to-one, with their approximations."""
    major, minor = (float(v) for v in s.beam.divergence_mrad)
    div = major
    if not math.isclose(major, minor, rel_tol=1e-12):
        div = math.sqrt(major * minor)
        col.add(_key("beam", "divergence_mrad"),
                f"HELIOS++ has no elliptical beam, the survey's is {major:g} × {minor:g} mrad",
                f"a circular beam of {div:.6g} mrad (the geometric mean)")
    opts = DetectorOptions.from_dict(survey.detector)
    ref = DetectorOptions.from_dict({"mode": "helios_v1"})
    diff = [f"{f.name}: {getattr(opts, f.name)}" for f in dataclasses.fields(DetectorOptions)
            if getattr(opts, f.name) != getattr(ref, f.name)]
    if diff:
        col.add("detector", f"HELIOS++ has one detector, the helios_v1 switches; the survey sets {', '.join(diff)}",
                "HELIOS++'s own detector")
    threshold = _HELIOS_THRESHOLD
    if s.detector.min_energy > 0:
        threshold = float(s.detector.min_energy)
        if not math.isclose(threshold, _HELIOS_THRESHOLD, rel_tol=1e-12):
            col.add(_key("detector", "min_energy"),
                    f"HELIOS++ 1.0.8's detection threshold is fixed at {_HELIOS_THRESHOLD:g}, "
                    f"the survey's is {threshold:g}", "receivedEnergyMin_W, read by HELIOS++ 2.x only")
    if survey.noise.enabled:
        col.add("trajectory_noise", "HELIOS++'s platform noise is white noise with a lifespan, not the "
                "survey's smooth trajectory error", "no trajectory noise")
    prf = col.integer(s.emitter.prf_hz, _key("emitter", "prf_hz"), "pulse frequency")
    wavelength = col.integer(s.emitter.wavelength_nm, _key("emitter", "wavelength_nm"), "wavelength (nm)")
    return {"divergence_mrad": div, "threshold": threshold, "prf": prf, "wavelength": wavelength}


def _scanner_element(s: ScannerSettings, optics: _Optics, vals: dict) -> ET.Element:
    det, beam = s.detector, s.beam
    attrs = {
        "id": _ident(s.name), "name": f"{s.name} (vlsforest scanner settings)", "optics": optics.optics,
        "pulseFreqs_Hz": str(vals["prf"]), "beamDivergence_rad": vals["divergence_mrad"] / 1000.0,
        "pulseLength_ns": s.emitter.pulse_length_ns, "accuracy_m": det.range_noise_m, "rangeMin_m": det.range_min_m,
        "scanAngleMax_deg": optics.angle_max_deg,
    }
    if optics.angle_effective_deg is not None:
        attrs["scanAngleEffectiveMax_deg"] = optics.angle_effective_deg
    attrs.update({"scanFreqMin_Hz": 0, "scanFreqMax_Hz": optics.scan_freq_hz})
    if optics.optics == "oscillating":
        attrs["scanProduct"] = max(_SCAN_PRODUCT, int(math.ceil(optics.angle_max_deg * optics.scan_freq_hz)))
    attrs.update({
        "headRotatePerSecMax_deg": optics.head_speed_deg, "wavelength_nm": vals["wavelength"],
        "averagePower_w": s.emitter.average_power_w, "beamQualityFactor": beam.quality_factor,
        "opticalEfficiency": det.optical_efficiency, "receiverDiameter_m": det.receiver_diameter_m,
        "atmosphericVisibility_km": (s.atmosphere.visibility_km if s.atmosphere.enabled
                                     else NO_ATMOSPHERE_VISIBILITY_KM),
        "maxNOR": int(det.max_returns), "receivedEnergyMin_W": vals["threshold"],
    })
    el = _element("scanner", attrs)
    origin = _element("beamOrigin", {"x": 0, "y": 0, "z": 0}, el)
    if optics.emitter_tilt_deg != 0:
        _element("rot", {"axis": "x", "angle_deg": optics.emitter_tilt_deg}, origin)
    _element("headRotateAxis", {"x": 0, "y": 0, "z": optics.head_axis_z}, el)
    _element("FWFSettings", _fwf(s), el)
    return el


def _fwf(s: ScannerSettings) -> dict:
    return {"binSize_ns": s.detector.bin_size_ns, "winSize_ns": s.detector.window_size_ns,
            "beamSampleQuality": int(s.beam.sample_quality)}


def _linear_waypoints(survey: Survey) -> list[dict]:
    """The HELIOS++ waypoints of a linear survey (see the module docstring), in order."""
    out = []
    prev = None
    for i, lg in enumerate(survey.legs):
        start, end = np.asarray(lg.start, np.float64), np.asarray(lg.end, np.float64)
        if prev is not None and not np.array_equal(start, prev):
            out.append({"xyz": prev, "active": False, "speed": lg.speed_mps, "note": f"transit to leg {i}",
                        "toward": start, "key": f"the transit to platform.legs[{i}]"})
        out.append({"xyz": start, "active": bool(lg.active), "speed": lg.speed_mps,
                    "note": f"leg {i} ({'active' if lg.active else 'inactive'})", "toward": end,
                    "key": f"platform.legs[{i}]"})
        prev = end
    last = survey.legs[-1]
    out.append({"xyz": prev, "active": False, "speed": last.speed_mps, "note": f"end of leg {len(survey.legs) - 1}",
                "toward": None, "key": ""})
    for w in out:
        if w["toward"] is None:
            continue
        d = w["toward"] - w["xyz"]
        if math.hypot(d[0], d[1]) <= 1e-9 * float(np.linalg.norm(d)):
            raise ConfigError(f"{w['key']} is vertical: HELIOS++'s linear platform turns to face its next "
                              "waypoint horizontally and cannot fly it")
    return out


def _static_mount_tilt(survey: Survey, col: _Collector) -> float:
    tilts = [float(p.tilt_deg) for p in survey.positions]
    t0 = tilts[0]
    turned = any(float(p.heading_deg) != 0 for p in survey.positions)
    if any(t != t0 for t in tilts) or (t0 != 0 and turned):
        col.add("platform.positions[].tilt_deg",
                "HELIOS++ tilts the scanner once per platform (its mount), below the head's rotation",
                f"the first position's tilt ({t0:g}°) in the mount for every position, headings as head angles")
    return t0


def survey_documents(survey: Survey, *, name: str = "vlsforest_survey", scene: str = f"{SCENE_FILE}#vlsforest_scene",
                     trajectory_interval_s: float = 0.0, allow_approximations: bool = False) -> SurveyXml:
    """The HELIOS++ survey, scanner and platform XML of a survey.

    Parameters
    ----------
    survey : Survey
        A parsed survey (:func:`vlsforest.sim.load_survey`).
    name : str
        The survey's name in HELIOS++ (its output folder).
    scene : str
        The scene's location, ``file.xml#scene_id``.
    trajectory_interval_s : float
        HELIOS++'s trajectory output interval (0: none).
    allow_approximations : bool
        Write what HELIOS++ cannot run as the documented downgrade (module docstring) instead of
        raising.

    Returns
    -------
    SurveyXml

    Raises
    ------
    ConfigError
        For a setting HELIOS++ cannot run (the first, naming its key) unless
        ``allow_approximations``; for a vertical linear leg; for a bad ``detector`` section or a
        negative ``trajectory_interval_s``.
    """
    if not (math.isfinite(trajectory_interval_s) and trajectory_interval_s >= 0):
        raise ConfigError(f"the trajectory interval must be ≥ 0 s, got {trajectory_interval_s!r}")
    s = survey.scanner
    col = _Collector()
    vals = _scanner_approximations(s, survey, col)
    optics = _optics(s, vals["prf"], col)
    linear = survey.platform_type == "linear"
    waypoints = _linear_waypoints(survey) if linear else None
    tilt = 0.0 if linear else _static_mount_tilt(survey, col)
    if col.items and not allow_approximations:
        first = col.items[0]
        more = f" (and {len(col.items) - 1} more)" if len(col.items) > 1 else ""
        raise ConfigError(f"{first.key}: HELIOS++ cannot run it: {first.problem}{more}; with approximations "
                          f"allowed (--allow-approximations) it is written as {first.written}")
    notes = [f"approximation: {a}" for a in col.items]

    scanner_id, platform_id = _ident(s.name), "vlsforest_linear" if linear else "vlsforest_static"
    sv = _element("survey", {"name": name, "scene": scene, "platform": f"{PLATFORM_FILE}#{platform_id}",
                             "scanner": f"{SCANNER_FILE}#{scanner_id}", "seed": str(int(survey.seed))})
    _element("FWFSettings", _fwf(s), sv)
    settings = {"pulseFreq_hz": vals["prf"], "scanAngle_deg": optics.scan_angle_deg, "scanFreq_hz": optics.scan_freq_hz}
    if linear:
        for w in waypoints:
            sv.append(_comment(w["note"]))
            leg = _element("leg", {}, sv)
            x, y, z = (float(c) for c in w["xyz"])
            _element("platformSettings", {"x": x, "y": y, "z": z, "onGround": False, "movePerSec_m": w["speed"]}, leg)
            _element("scannerSettings", {"active": w["active"], **settings, "headRotatePerSec_deg": 0,
                                         "headRotateStart_deg": 0, "headRotateStop_deg": 0,
                                         "trajectoryTimeInterval_s": trajectory_interval_s}, leg)
    else:
        n_az = len(tls_grid(s.tls)[0])
        for i, p in enumerate(survey.positions):
            sv.append(_comment(f"scan position {i}"))
            leg = _element("leg", {}, sv)
            x, y, z = (float(c) for c in p.position)
            start = float(s.tls.h_fov_deg[0]) + float(p.heading_deg)
            _element("platformSettings", {"x": x, "y": y, "z": z, "onGround": False}, leg)
            _element("scannerSettings", {"active": True, **settings, "headRotatePerSec_deg": optics.head_speed_deg,
                                         "headRotateStart_deg": start,
                                         "headRotateStop_deg": start + n_az * optics.head_step_deg,
                                         "trajectoryTimeInterval_s": trajectory_interval_s}, leg)
    header = [f"survey written by vlsforest; run it from this folder: helios {SURVEY_FILE}"]
    survey_xml = _document(sv, header + notes)

    scanner_xml = _document(_scanner_element(s, optics, vals), [f"the scanner of the survey {name} as it runs"] + notes)

    pf = _element("platform", {"id": platform_id, "name": "vlsforest " + ("linear path" if linear else "static"),
                               "type": "linearpath" if linear else "static"})
    mount = _element("scannerMount", {"x": 0, "y": 0, "z": 0}, pf)
    if linear:  # beam of deflection a: (sin a, 0, -cos a) in the platform frame, right of the track for a > 0
        _element("rot", {"axis": "x", "angle_deg": -90}, mount)
        _element("rot", {"axis": "z", "angle_deg": -90}, mount)
    elif tilt != 0:
        _element("rot", {"axis": "x", "angle_deg": tilt}, mount)
    platform_xml = _document(pf, ["the scanner sits at the waypoints; rotations apply in order about fixed axes"])
    return SurveyXml(survey_xml, scanner_xml, platform_xml, tuple(col.items))


def export_survey(scene_yaml, survey_yaml, out_dir, *, name: str | None = None, scene_id: str = "vlsforest_scene",
                  trajectory_interval_s: float = 0.0, allow_approximations: bool = False):
    """Write a scene and a survey as one HELIOS++ folder, whole or not at all.

    Parameters
    ----------
    scene_yaml, survey_yaml : path
        The SCENE.yaml and SURVEY.yaml that ``vlsforest simulate`` runs.
    out_dir : path
        The folder: ``scene.xml`` and its parts, ``survey.xml``, ``scanner.xml``,
        ``platform.xml``. Run it with ``cd out_dir && helios survey.xml``.
    name : str, optional
        The survey's name (default: the SURVEY.yaml's file name without suffix).
    scene_id : str
        The XML scene id.
    trajectory_interval_s : float
        HELIOS++'s trajectory output interval (0: none).
    allow_approximations : bool
        See :func:`survey_documents`.

    Returns
    -------
    path : Path
        ``out_dir/survey.xml``.
    approximations : tuple of Approximation
        What was written in place of settings HELIOS++ cannot run (empty unless allowed).

    Raises
    ------
    ConfigError
        A survey HELIOS++ cannot run (see :func:`survey_documents`), raised before anything is
        written; the survey and scene readers' errors.
    """
    from vlsforest.io.atomic import atomic_dir, write_text

    survey_yaml = Path(survey_yaml)
    survey = load_survey(survey_yaml)
    try:
        docs = survey_documents(survey, name=name or survey_yaml.stem, scene=f"{SCENE_FILE}#{scene_id}",
                                trajectory_interval_s=trajectory_interval_s,
                                allow_approximations=allow_approximations)
    except ConfigError as exc:
        raise ConfigError(f"{survey_yaml}: {exc}") from None
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        write_scene_xml(scene_yaml, tmp, scene_id)
        write_text(tmp / SURVEY_FILE, docs.survey)
        write_text(tmp / SCANNER_FILE, docs.scanner)
        write_text(tmp / PLATFORM_FILE, docs.platform)
    return out_dir / SURVEY_FILE, docs.approximations
