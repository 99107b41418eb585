"""What a real prism shot has that the ideal virtual camera lacks: right-view gain
and colour cast, vignetting, lens PSF, JPEG, and flash highlights (:class:`CameraEffects`,
applied by :func:`~prism3d.capture.simulate.simulate_shot`; order and model:
docs/capture.md, "Camera effects"). Ground truth stays diffuse-only and effect-free.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_in_range
from prism3d.errors import InputError

__all__ = ["CameraEffects", "Gloss", "MATERIALS", "jpeg_roundtrip", "vignetting_factor"]


@dataclass(frozen=True)
class Gloss:
    """Blinn-Phong flash highlight of a material class: ``coefficient * (n . h)^shininess * k rgb``
    added to a pixel, ``h`` bisecting the directions to camera and flash (light-coloured).

    References
    ----------
    .. [1] J. F. Blinn, "Models of light reflection for computer synthesized
       pictures", SIGGRAPH 1977.
    """

    coefficient: float
    """Peak specular reflectance (``n . h = 1``) relative to a white diffuse surface, in [0, 1]."""
    shininess: float
    """Blinn-Phong exponent >= 1 (lobe half-width ``arccos(0.5 ** (1 / shininess))``)."""

    def __post_init__(self) -> None:
        ks = check_in_range(self.coefficient, "gloss coefficient", 0.0, 1.0)
        object.__setattr__(self, "coefficient", ks)
        object.__setattr__(self, "shininess", check_in_range(self.shininess, "gloss shininess", 1.0, 1e6))


#: Gloss of the material classes a mesh may name in ``SceneMesh.metadata["material"]``
#: (why these values: docs/capture.md, "Camera effects").
MATERIALS: Mapping[str, Gloss] = MappingProxyType(
    {
        "painted_metal": Gloss(0.06, 200.0),
        "matte_paint": Gloss(0.02, 20.0),
        "gloss_paint": Gloss(0.10, 2000.0),
        "matte_paper": Gloss(0.01, 10.0),
        "lambertian": Gloss(0.0, 1.0),
    }
)


def _gain3(value: Any, name: str) -> tuple[float, float, float]:
    a = check_array(value, name, shape=(3,), dtype_kind="fiu")
    return tuple(check_in_range(float(v), name, 0.05, 4.0) for v in a)  # type: ignore[return-value]


@dataclass(frozen=True)
class CameraEffects:
    """Real-camera effects of the virtual prism rig; defaults are plausible values
    whose sources are in docs/capture.md ("Camera effects")."""

    exposure_right: float = 0.88
    """Gain of the right view relative to the left (its prism/mirror path loses light)."""
    colour_gain_right: tuple[float, float, float] = (0.96, 1.0, 1.04)
    """Extra (R, G, B) gain of the right view: the colour cast of mirror coatings and glass."""
    vignetting_stops: float = 0.5
    """Fall-off at a view's farthest corner, stops: ``V = 1 - (1 - 2^-stops) (r / r_corner)^2``
    about the view's principal point (corner at 71 % by default)."""
    psf_sigma_px: float = 0.7
    """Gaussian lens PSF per view, px, before noise (``hypot`` with ``blur_sigma``)."""
    jpeg_quality: int | None = 92
    """JPEG quality 1-100 of the sensor image (OpenCV, 4:2:0), after noise; None = lossless."""
    materials: tuple[tuple[str, Gloss], ...] = field(default_factory=lambda: tuple(MATERIALS.items()))
    """Gloss per material class (default :data:`MATERIALS`), named by ``metadata["material"]``."""
    default_material: str = "painted_metal"
    """Class of meshes that name none (targets are painted metal)."""
    specular: bool = True
    """Add the view-dependent flash highlights."""

    def __post_init__(self) -> None:
        setv = object.__setattr__
        setv(self, "exposure_right", check_in_range(self.exposure_right, "exposure_right", 0.05, 4.0))
        setv(self, "colour_gain_right", _gain3(self.colour_gain_right, "colour_gain_right"))
        setv(self, "vignetting_stops", check_in_range(self.vignetting_stops, "vignetting_stops", 0.0, 6.0))
        setv(self, "psf_sigma_px", check_in_range(self.psf_sigma_px, "psf_sigma_px", 0.0, 20.0))
        q = self.jpeg_quality
        if q is not None:
            if isinstance(q, bool) or int(q) != q or not 1 <= int(q) <= 100:
                raise InputError(f"jpeg_quality: expected an integer in [1, 100] or None, got {q!r}")
            setv(self, "jpeg_quality", int(q))
        items = self.materials.items() if isinstance(self.materials, Mapping) else self.materials
        try:
            mats = tuple((str(n), g) for n, g in items)
        except (TypeError, ValueError) as exc:
            raise InputError("materials: expected (name, Gloss) pairs") from exc
        for n, g in mats:
            if not isinstance(g, Gloss):
                raise InputError(f"materials[{n!r}]: expected a Gloss, got {type(g).__name__}")
        names = [n for n, _ in mats]
        if len(set(names)) != len(names):
            raise InputError(f"materials: duplicate class names in {names}")
        setv(self, "materials", mats)
        if self.default_material not in names:
            raise InputError(
                f"default_material: {self.default_material!r} is not one of {', '.join(names)}"
            )
        setv(self, "specular", bool(self.specular))

    @classmethod
    def ideal(cls) -> CameraEffects:
        """The ideal camera: equal views, no vignetting, no PSF, no JPEG, no gloss."""
        return cls(1.0, (1.0, 1.0, 1.0), 0.0, 0.0, None, specular=False)

    @property
    def is_ideal(self) -> bool:
        """True when every effect is neutral (the shot is the old ideal one)."""
        return (
            self.exposure_right == 1.0
            and self.colour_gain_right == (1.0, 1.0, 1.0)
            and self.vignetting_stops == 0.0
            and self.psf_sigma_px == 0.0
            and self.jpeg_quality is None
            and not self.has_gloss
        )

    @property
    def has_gloss(self) -> bool:
        """Whether any material may add a highlight."""
        return self.specular and any(g.coefficient > 0 for _, g in self.materials)

    def gloss(self, material: str | None) -> Gloss:
        """The gloss of a material class (``None`` = ``default_material``)."""
        name = self.default_material if material is None else material
        for n, g in self.materials:
            if n == name:
                return g
        known = ", ".join(n for n, _ in self.materials)
        raise InputError(f"material {name!r}: unknown class; known classes: {known}")

    def view_gain(self, view: str) -> NDArray[np.float64]:
        """``(3,)`` RGB gain of ``"left"`` (ones) or ``"right"`` (exposure x colour)."""
        if view == "left":
            return np.ones(3)
        if view == "right":
            return self.exposure_right * np.asarray(self.colour_gain_right, dtype=np.float64)
        raise InputError(f"view: expected 'left' or 'right', got {view!r}")

    def vignetting_coefficients(
        self, size: tuple[int, int], principal_point: tuple[float, float]
    ) -> tuple[float, float]:
        """``(a, 1 / r_corner^2)`` of ``V = 1 - a r^2 / r_corner^2`` for a view of
        ``size`` ``(W, H)`` with principal point ``(cx, cy)`` (view pixels);
        ``r_corner`` reaches the farthest corner pixel centre."""
        w, h = int(size[0]), int(size[1])
        cx, cy = float(principal_point[0]), float(principal_point[1])
        rc2 = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0.0, w - 1.0) for y in (0.0, h - 1.0))
        a = 1.0 - 2.0 ** (-self.vignetting_stops)
        return a, (1.0 / rc2 if rc2 > 0 else 0.0)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready values (``materials`` as ``{name: [coefficient, shininess]}``)."""
        return {
            "exposure_right": self.exposure_right,
            "colour_gain_right": list(self.colour_gain_right),
            "vignetting_stops": self.vignetting_stops,
            "psf_sigma_px": self.psf_sigma_px,
            "jpeg_quality": self.jpeg_quality,
            "materials": {n: [g.coefficient, g.shininess] for n, g in self.materials},
            "default_material": self.default_material,
            "specular": self.specular,
        }

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> CameraEffects:
        """Inverse of :meth:`to_dict`; unknown keys are an error, missing ones default."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise InputError(
                f"camera effects: unknown keys {', '.join(unknown)}; known: {', '.join(sorted(known))}"
            )
        kw = dict(values)
        if "materials" in kw:
            try:
                mats = dict(kw["materials"]).items()
                kw["materials"] = tuple((str(n), Gloss(*v)) for n, v in mats)
            except (TypeError, ValueError) as exc:
                raise InputError(
                    "camera effects: materials must map names to [coefficient, shininess]"
                ) from exc
        if "colour_gain_right" in kw:
            kw["colour_gain_right"] = tuple(kw["colour_gain_right"])
        return cls(**kw)


def vignetting_factor(
    size: tuple[int, int], principal_point: tuple[float, float], stops: float
) -> NDArray[np.float64]:
    """``(H, W)`` relative illumination ``V(r)`` of a ``(W, H)`` view with principal
    point ``(cx, cy)`` (the reference of the simulator's kernel)."""
    fx = CameraEffects(vignetting_stops=stops)
    a, inv_rc2 = fx.vignetting_coefficients(size, principal_point)
    u = np.arange(int(size[0])) - float(principal_point[0])
    v = np.arange(int(size[1])) - float(principal_point[1])
    return 1.0 - a * (u[None, :] ** 2 + v[:, None] ** 2) * inv_rc2


def jpeg_roundtrip(image: NDArray[np.uint8], quality: int) -> NDArray[np.uint8]:
    """Encode an RGB image as JPEG in memory (OpenCV, default 4:2:0 chroma
    subsampling) at ``quality`` and decode it: ``(H, W, 3) uint8`` in, same out."""
    import cv2

    img = check_array(image, "image", ndim=3, dtype_kind="u")
    if img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"image: expected (H, W, 3) uint8, got {img.shape} {img.dtype}")
    q = int(quality)
    if q != quality or not 1 <= q <= 100:
        raise InputError(f"quality: expected an integer in [1, 100], got {quality!r}")
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, q])
    if not ok:
        raise InputError("image: OpenCV could not encode it as JPEG")
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return np.ascontiguousarray(out[:, :, ::-1])
