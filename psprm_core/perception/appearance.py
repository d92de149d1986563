"""Target appearances: what the renderer draws for a target, looked up by name.

An :class:`Appearance` is a small set of :class:`Part` s (boxes or front-facing textured quads) laid out in the
target's *normalised* box (each coordinate in [-0.5, 0.5], scaled by the target's ``size``), so everything drawn stays
inside the target's box and the projected target box bounds the rendered pixels. The target's +x axis is the side it
faces; photos go on a quad on that side (visible from the front half-space only, as TinyRenderer culls back faces).

Images come from packages that ship them (scikit-image's sample photos, matplotlib's sample data) or are drawn
procedurally with numpy; nothing is downloaded. Use :func:`list_appearances` for the names and
``docs/detectors.md`` for the confidences the real detectors give each appearance.
"""

from __future__ import annotations

import functools

import logging
from dataclasses import dataclass, field
from typing import Callable, Dict, Optional, Tuple

import numpy as np
from ..geometry import matrix_to_quat, rpy_to_matrix

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------------------------
# Data types
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Photo:
    """An image source plus the region that must stay in view when the image is cropped to a quad's aspect.

    Attributes
    ----------
    loader : callable
        Returns an ``(H, W, 3)`` uint8 RGB image.
    focus : (x1, y1, x2, y2) or None
        Region (pixels of the loaded image) to keep; the crop is centred on it. ``None`` keeps the whole image.
    fill : float
        Fraction of the crop's limiting dimension the focus region should occupy (1 = tight crop).
    """

    loader: Callable[[], np.ndarray]
    focus: Optional[Tuple[float, float, float, float]] = None
    fill: float = 1.0


@dataclass(frozen=True)
class Part:
    """One piece of a target's geometry, in normalised target coordinates.

    Attributes
    ----------
    center : (3,) tuple
        Centre, each coordinate in [-0.5, 0.5] (multiplied by the target's size).
    size : (3,) tuple
        Extents as fractions of the target's size. A ``"quad"`` uses only y (width) and z (height).
    color : (4,) tuple
        RGBA for untextured parts.
    image : str or None
        Key of a :class:`Photo` in the appearance's ``photos``.
    kind : {"box", "quad", "cylinder"}
        A quad is a single rectangle in the part's y-z plane facing +x; a cylinder's axis is the part's z axis and
        its radius half the smaller of its x/y extents.
    quat : (4,) tuple
        Orientation (x, y, z, w) in the target frame.
    """

    center: Tuple[float, float, float]
    size: Tuple[float, float, float]
    color: Tuple[float, float, float, float] = (0.5, 0.5, 0.5, 1.0)
    image: Optional[str] = None
    kind: str = "box"
    quat: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Appearance:
    """A named look for targets.

    Attributes
    ----------
    name : str
    classes : tuple of str
        Detector classes this appearance is meant to be recognised as.
    parts : tuple of Part
    photos : dict
        ``key -> Photo`` for the textured parts.
    description : str
        Where the images come from and what the geometry is.
    """

    name: str
    classes: Tuple[str, ...]
    parts: Tuple[Part, ...]
    photos: Dict[str, Photo] = field(default_factory=dict)
    description: str = ""

    def parts_for(self, size) -> Tuple[Part, ...]:
        """The parts to build for a target of the given size (currently size-independent)."""
        return self.parts

    def texture(self, key: str, aspect: float) -> np.ndarray:
        """Image for photo ``key`` cropped around its focus to ``aspect`` (= width / height of the quad)."""
        photo = self.photos[key]
        return crop_to_aspect(np.asarray(photo.loader())[..., :3].astype(np.uint8), aspect, photo.focus, photo.fill)


def crop_to_aspect(img: np.ndarray, aspect: float, focus=None, fill: float = 1.0) -> np.ndarray:
    """Crop ``img`` to ``aspect`` (width / height) around ``focus`` (x1, y1, x2, y2), padding with edge pixels.

    The crop is the smallest window of that aspect that contains the focus region enlarged by ``1 / fill``.
    """
    h, w = img.shape[:2]
    x1, y1, x2, y2 = (0, 0, w, h) if focus is None else focus
    cx, cy = 0.5 * (x1 + x2), 0.5 * (y1 + y2)
    fw, fh = (x2 - x1) / fill, (y2 - y1) / fill
    if focus is None:
        fw, fh = w, h
    cw = max(fw, fh * aspect)
    ch = cw / aspect
    if focus is None:  # whole image: largest centred window of that aspect
        cw, ch = (w, w / aspect) if w / aspect <= h else (h * aspect, h)
    xa, ya = int(round(cx - cw / 2)), int(round(cy - ch / 2))
    xb, yb = int(round(cx + cw / 2)), int(round(cy + ch / 2))
    pad = max(0, -xa, -ya, xb - w, yb - h)
    if pad:
        img = np.pad(img, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
        xa, xb, ya, yb = xa + pad, xb + pad, ya + pad, yb + pad
    return np.ascontiguousarray(img[ya:yb, xa:xb])


# ------------------------------------------------------------------------------------------------------------------
# Image sources (loaded on demand)
# ------------------------------------------------------------------------------------------------------------------
def _skimage(name: str) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        try:
            import skimage.data
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError("appearance photos need scikit-image: run scripts/install_detectors.sh") from exc
        return getattr(skimage.data, name)()

    load.__name__ = f"skimage.data.{name}"
    return load


def _mpl_sample(fname: str) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        from matplotlib import cbook
        from PIL import Image

        with cbook.get_sample_data(fname) as fh:
            return np.asarray(Image.open(fh).convert("RGB"))

    load.__name__ = f"matplotlib sample_data/{fname}"
    return load


def _procedural(fn: Callable[[np.random.Generator], np.ndarray], seed: int = 0) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        return fn(np.random.default_rng(seed))

    load.__name__ = fn.__name__
    return load


def draw_suitcase_shell(rng: np.random.Generator, size: int = 384) -> np.ndarray:
    """Front of a red hard-shell suitcase filling the image: highlight, four vertical ribs and a zipper line."""
    h = w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    base = np.array([0.7, 0.1, 0.1])
    img = base * (0.75 + 0.35 * np.exp(-((xx - 0.35 * w) / (0.3 * w)) ** 2))[..., None]
    for k in range(1, 5):
        img[np.abs(xx - k * w / 5) < 3] = base * 0.6
    img[np.abs(yy - 8) < 2] = 0.75
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def _plant_parts(n_leaves: int = 120, seed: int = 1) -> tuple:
    """A terracotta pot (cylinder) with ``n_leaves`` thin green boxes radiating from the soil."""
    rng = np.random.default_rng(seed)
    parts = [Part(center=(0, 0, -0.33), size=(0.6, 0.6, 0.34), color=(0.72, 0.36, 0.2, 1.0), kind="cylinder"),
             Part(center=(0, 0, -0.155), size=(0.56, 0.56, 0.01), color=(0.25, 0.17, 0.1, 1.0), kind="cylinder")]
    for _ in range(n_leaves):
        az, el, length = rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 1.3), rng.uniform(0.25, 0.4)
        d = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        c = np.clip(np.array([0, 0, -0.15]) + d * length * 0.55, -0.45, 0.45)
        q = matrix_to_quat(rpy_to_matrix((rng.uniform(-0.5, 0.5), -el, az)))
        g = rng.uniform(0.3, 0.6)
        parts.append(Part(center=tuple(c), size=(length * 0.5, 0.07, 0.012), color=(g * 0.35, g, g * 0.25, 1.0),
                          quat=tuple(q)))
    return tuple(parts)


def draw_fork(rng: np.random.Generator, size: int = 384) -> np.ndarray:
    """A steel fork (four tines, neck, handle) lying on a wooden table seen from above."""
    h = w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    wood = 0.55 + 0.08 * np.sin(yy / 7.0 + 3 * np.sin(xx / 40.0)) + 0.03 * rng.standard_normal((h, w))
    img = np.stack([wood * 0.85, wood * 0.55, wood * 0.32], axis=-1)
    cx = w / 2
    steel = np.array([0.80, 0.81, 0.84])
    handle = (np.abs(xx - cx) < 0.035 * w + 0.02 * w * (yy - 0.55 * h) / (0.4 * h)) & (yy > 0.50 * h) & (yy < 0.95 * h)
    neck = (np.abs(xx - cx) < 0.03 * w) & (yy > 0.36 * h) & (yy <= 0.50 * h)
    head = (np.abs(xx - cx) < 0.075 * w) & (yy > 0.30 * h) & (yy <= 0.38 * h)
    tines = np.zeros_like(head)
    for k in range(4):
        tx = cx - 0.06 * w + k * 0.04 * w
        tines |= (np.abs(xx - tx) < 0.011 * w) & (yy > 0.06 * h) & (yy <= 0.31 * h)
    metal = handle | neck | head | tines
    light = 0.85 + 0.25 * np.cos((xx - cx) / (0.05 * w))
    img[metal] = steel * np.clip(light[metal, None], 0.6, 1.1)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def draw_screen(rng: np.random.Generator, size: int = 384) -> np.ndarray:
    """A desktop-like screen image: coloured wallpaper gradient with a few windows."""
    h, w = int(size * 0.6), size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    img = np.stack([0.15 + 0.3 * xx / w, 0.35 + 0.2 * yy / h, 0.7 - 0.2 * xx / w], axis=-1)
    for _ in range(4):
        x1, y1 = rng.uniform(0.05, 0.6) * w, rng.uniform(0.05, 0.5) * h
        ww, hh = rng.uniform(0.2, 0.35) * w, rng.uniform(0.25, 0.4) * h
        win = (xx > x1) & (xx < x1 + ww) & (yy > y1) & (yy < y1 + hh)
        img[win] = (0.95, 0.95, 0.95)
        img[win & (yy < y1 + 0.06 * h)] = (0.3, 0.3, 0.35)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------------------------------
# Catalogue
# ------------------------------------------------------------------------------------------------------------------
def _photo_board(name: str, classes, photo: Photo, board_color, description: str) -> Appearance:
    """A coloured block filling the target box with a photo quad on its +x face."""
    return Appearance(
        name=name, classes=tuple(classes),
        parts=(Part(center=(-0.01, 0.0, 0.0), size=(0.98, 1.0, 1.0), color=tuple(board_color)),
               Part(center=(0.5, 0.0, 0.0), size=(0.0, 1.0, 1.0), image="front", kind="quad")),
        photos={"front": photo}, description=description)


def _monitor(name: str, screen: Photo, description: str, stand: bool = False) -> Appearance:
    """Flat monitor: a dark bezel box filling the target box with the screen quad on its +x face. With
    ``stand=True`` the bezel takes the upper 3/4 and a foot and neck fill the lower quarter."""
    if stand:
        parts = (
            Part(center=(-0.1, 0.0, -0.48), size=(0.7, 0.45, 0.04), color=(0.08, 0.08, 0.09, 1.0)),
            Part(center=(-0.25, 0.0, -0.36), size=(0.2, 0.1, 0.22), color=(0.1, 0.1, 0.11, 1.0)),
            Part(center=(0.0, 0.0, 0.13), size=(0.4, 1.0, 0.74), color=(0.05, 0.05, 0.06, 1.0)),
            Part(center=(0.2005, 0.0, 0.14), size=(0.0, 0.96, 0.68), image="screen", kind="quad"),
        )
    else:
        parts = (
            Part(center=(-0.01, 0.0, 0.0), size=(0.98, 1.0, 1.0), color=(0.05, 0.05, 0.06, 1.0)),
            Part(center=(0.5, 0.0, 0.0), size=(0.0, 0.95, 0.92), image="screen", kind="quad"),
        )
    return Appearance(name=name, classes=("tv",), parts=parts, photos={"screen": screen}, description=description)


def draw_dark_screen(rng: np.random.Generator, size: int = 384) -> np.ndarray:
    """A switched-off screen: near-black with a faint diagonal reflection."""
    h, w = int(size * 0.6), size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    img = np.stack([0.06 + 0.10 * (1 - yy / h) * (xx / w)] * 3, axis=-1)
    img[..., 2] += 0.03
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


@functools.lru_cache(maxsize=1)  # built on first use (photos decoded once); appearances are read-only
def _catalogue() -> Dict[str, Appearance]:
    hair = (0.23, 0.17, 0.12, 1.0)
    white = (0.93, 0.93, 0.92, 1.0)
    dark = (0.1, 0.1, 0.1, 1.0)
    apps = [
        _photo_board("astronaut", ["face", "person"], Photo(_skimage("astronaut"), (170, 35, 285, 200), 0.85), hair,
                     "Eileen Collins' portrait, skimage.data.astronaut() (public domain, NASA), cropped to the head"),
        _photo_board("grace_hopper", ["face", "person"], Photo(_mpl_sample("grace_hopper.jpg"), (165, 95, 365, 345),
                                                               0.85), (0.85, 0.85, 0.85, 1.0),
                     "Grace Hopper's portrait shipped in matplotlib's sample_data, cropped to the head"),
        _photo_board("coffee", ["cup"], Photo(_skimage("coffee")), (0.55, 0.18, 0.12, 1.0),
                     "the whole skimage.data.coffee() photo (CC0; espresso cup, saucer, wooden table) on a board; "
                     "size the target about 0.3 m x 0.2 m (y x z) for detections at 1-2 m"),
        _photo_board("coffee_crop", ["cup"], Photo(_skimage("coffee"), (160, 15, 420, 300), 0.95),
                     (0.55, 0.18, 0.12, 1.0), "skimage.data.coffee() cropped to the cup (weak: only very close)"),
        Appearance(
            name="mug", classes=("cup",),
            parts=(Part(center=(0.0, -0.1, -0.05), size=(0.8, 0.8, 0.9), color=white, kind="cylinder"),
                   Part(center=(0.0, -0.1, 0.401), size=(0.68, 0.68, 0.02), color=(0.25, 0.13, 0.07, 1.0),
                        kind="cylinder")),
            description="white 3-D mug (cylinder) with coffee; only detected closer than ~0.7 m"),
        _monitor("monitor", Photo(_procedural(draw_dark_screen)),
                 "flat screen switched off: dark bezel filling the target box, near-black screen (stand separate)"),
        _monitor("monitor_stand", Photo(_procedural(draw_dark_screen)),
                 "monitor with its own stand in the box's lower quarter, screen switched off", stand=True),
        _monitor("monitor_on", Photo(_procedural(draw_screen)),
                 "flat screen showing a drawn desktop (weaker than 'monitor')"),
        Appearance(name="potted_plant", classes=("potted plant",), parts=_plant_parts(),
                   description="3-D plant: terracotta cylinder pot with 120 thin green leaf boxes (looks alike "
                               "from every side)"),
        Appearance(
            name="suitcase", classes=("suitcase",),
            parts=(Part(center=(0, 0, -0.06), size=(1, 1, 0.84), color=(0.7, 0.1, 0.1, 1.0)),
                   Part(center=(0.5, 0, -0.06), size=(0, 1, 0.84), image="front", kind="quad"),
                   Part(center=(-0.2, -0.2, 0.43), size=(0.1, 0.04, 0.18), color=dark),
                   Part(center=(-0.2, 0.2, 0.43), size=(0.1, 0.04, 0.18), color=dark),
                   Part(center=(-0.2, 0, 0.49), size=(0.12, 0.44, 0.03), color=dark),
                   Part(center=(0.0, 0, 0.375), size=(0.4, 0.3, 0.03), color=dark),
                   Part(center=(0.3, -0.4, -0.49), size=(0.2, 0.08, 0.03), color=dark),
                   Part(center=(0.3, 0.4, -0.49), size=(0.2, 0.08, 0.03), color=dark)),
            photos={"front": Photo(_procedural(draw_suitcase_shell))},
            description="3-D red hard-shell suitcase with telescopic grip (detected only at about 1 m, frontal)"),
        _photo_board("fork", ["fork"], Photo(_procedural(draw_fork)), (0.5, 0.33, 0.2, 1.0),
                     "procedurally drawn fork on wood (NOT detected by CenterNet)"),
        Appearance(name="plain", classes=(),
                   parts=(Part(center=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0), color=(0.9, 0.7, 0.2, 1.0)),),
                   description="an untextured yellow box (no detector should fire on it)"),
    ]
    return {a.name: a for a in apps}


#: Appearance used when a target names none, per detector class.
DEFAULT_FOR_CLASS = {
    "face": "astronaut",
    "person": "astronaut",
    "cup": "coffee",
    "tv": "monitor",
    "potted plant": "potted_plant",
    "suitcase": "suitcase",
    "fork": "fork",
}

#: Aliases accepted in scene files.
ALIASES = {
    "face_astronaut": "astronaut", "face_grace_hopper": "grace_hopper", "coffee_cup": "coffee",
    "nurse": "astronaut", "patient": "grace_hopper", "person": "astronaut", "face": "astronaut",
    "cup": "coffee", "tv": "monitor", "screen": "monitor", "plant": "potted_plant",
    "potted plant": "potted_plant",
}


def list_appearances() -> list:
    """Names of all built-in appearances (aliases excluded)."""
    return sorted(_catalogue())


def get_appearance(name: str = "", detector_class: str = "") -> Appearance:
    """Look up an appearance by name (or alias); an empty name picks the default for ``detector_class``.

    Unknown names fall back to the class default with a warning (and to ``"plain"`` if the class has none), so a
    scene with a typo still renders.
    """
    cat = _catalogue()
    key = (name or "").strip()
    key = ALIASES.get(key, key)
    if key in cat:
        return cat[key]
    fallback = DEFAULT_FOR_CLASS.get(detector_class, "plain")
    if key:
        log.warning("unknown appearance '%s' (known: %s); using '%s'", name, ", ".join(sorted(cat)), fallback)
    return cat[fallback]
