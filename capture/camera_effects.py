"""What a real prism shot has that the ideal virtual camera lacks.

The two halves of one sensor see the scene through different glass and mirrors, so
they differ in exposure, colour balance and vignetting; real surfaces are glossy,
real lenses blur and real files are JPEG. :class:`CameraEffects` collects these
effects with plausible values; :func:`~prism3d.capture.simulate.simulate_shot` applies
them (on by default) in this order::

    radiance = albedo * (ambient + k rgb) + gloss(n . h) * k rgb      (per ray, linear)
    view     = box-average -> gain_rgb(view) * vignetting(r) -> PSF blur
    sensor   = join views -> noise -> uint8 (saturates at 255) -> JPEG round trip

``k`` is the flash factor after the shadow test and ``rgb`` the projector colour
(see :mod:`prism3d.capture.simulate`); the gloss weight is evaluated on each output
pixel's centre ray and shared by its supersampled rays (the lobe spans hundreds of
pixels). With effects, radiance is not clipped per ray: the sensor saturates, so a
highlight bright enough reaches 255 in both views whatever their gains.
:meth:`CameraEffects.ideal` (or ``effects=None``) is the old ideal camera, exactly.

Ground truth (albedo, shading, illumination) stays diffuse-only and effect-free.
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
    """Blinn-Phong specular reflection of a material class under the flash.

    The specular radiance added to a pixel is ``coefficient * (n . h)^shininess * k rgb``
    with ``h`` the unit bisector of the directions to the camera and to the flash:
    light-coloured (paint is a dielectric: its highlight is not tinted by the
    pigment), strongest where the normal bisects the view and light directions.

    Attributes
    ----------
    coefficient : float
        Peak specular reflectance (``n . h = 1``) relative to a white diffuse
        surface, in [0, 1].
    shininess : float
        Blinn-Phong exponent (>= 1): the lobe falls to half at an angle
        ``arccos(0.5 ** (1 / shininess))`` between ``n`` and ``h`` (4.8 deg at 200).

    References
    ----------
    .. [1] J. F. Blinn, "Models of light reflection for computer synthesized
       pictures", SIGGRAPH 1977.
    """

    coefficient: float
    shininess: float

    def __post_init__(self) -> None:
        ks = check_in_range(self.coefficient, "gloss coefficient", 0.0, 1.0)
        object.__setattr__(self, "coefficient", ks)
        object.__setattr__(self, "shininess", check_in_range(self.shininess, "gloss shininess", 1.0, 1e6))


#: Gloss of the material classes a mesh may name in ``SceneMesh.metadata["material"]``.
#: ``painted_metal`` (the default): satin/semi-gloss enamel on steel, peak ~6 % (a
#: dielectric's Fresnel reflectance at normal incidence is ~4-5 %, roughness spreads
#: it), lobe half-width ~5 deg. ``matte_paint``: flat military paint (CARC-like, a
#: 60-deg gloss of a few GU), a weak broad sheen. ``gloss_paint``: car-like clear coat.
#: ``matte_paper``: a printed calibration board on matte stock. ``lambertian``: none.
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
    """Real-camera effects of the virtual prism rig (defaults: plausible values).

    Attributes
    ----------
    exposure_right : float
        Gain of the right view relative to the left (1 = equal). The two views
        reach the sensor over different prism and mirror paths: a front-surface
        aluminium mirror reflects ~88-92 %, a protected one less, and an extra
        reflection or a longer glass path costs a few % to ~15 %. Default 0.88.
    colour_gain_right : (float, float, float)
        Extra per-channel (R, G, B) gain of the right view: a colour cast, since
        mirror coatings and glass do not reflect/transmit all wavelengths equally
        (aluminium dips in the red near 800 nm, glass absorbs a little blue). A
        white balance set on one view leaves the other a few % off. Default
        (0.96, 1.0, 1.04).
    vignetting_stops : float
        Light fall-off at the corner of each view, in stops (0 = none), as
        ``V(r) = 1 - (1 - 2^-stops) (r / r_corner)^2`` (the leading term of the
        cos^4 law), ``r`` the distance from the view's principal point (its optical
        centre, not the sensor centre) and ``r_corner`` the distance to the view's
        farthest corner pixel centre. A 100 mm lens at a moderate aperture loses
        ~0.5-1 stop in the corners; the adapter's mirror edges add mechanical
        vignetting. Default 0.5 (corner at 71 %).
    psf_sigma_px : float
        Gaussian lens PSF of each view, standard deviation in pixels, applied
        before noise (combined with ``simulate_shot``'s ``blur_sigma`` as
        ``hypot(blur_sigma, psf_sigma_px)``). A good lens at 5 MP (2.2 um pixels)
        has a PSF of ~0.5-1 px sigma. Default 0.7.
    jpeg_quality : int or None
        JPEG quality (1-100) of the final sensor image, encoded and decoded in
        memory by OpenCV after noise and quantisation, as a camera does; None =
        lossless (no JPEG). OpenCV's default encoder subsamples chroma 4:2:0 (as
        most cameras do), which smears the colour grating a little. Cameras save
        at quality ~90-95. Default 92.
    materials : tuple of (str, Gloss)
        Specular gloss per material class (default: :data:`MATERIALS`); a mesh
        names its class in ``metadata["material"]``.
    default_material : str
        Class of meshes that name none. Default ``"painted_metal"`` (targets are
        painted metal: moderate gloss).
    specular : bool
        Add the flash highlights (view-dependent: they sit where the surface normal
        bisects the directions to the camera and to the flash, so the two views see
        them at different places). Default True.
    """

    exposure_right: float = 0.88
    colour_gain_right: tuple[float, float, float] = (0.96, 1.0, 1.04)
    vignetting_stops: float = 0.5
    psf_sigma_px: float = 0.7
    jpeg_quality: int | None = 92
    materials: tuple[tuple[str, Gloss], ...] = field(default_factory=lambda: tuple(MATERIALS.items()))
    default_material: str = "painted_metal"
    specular: bool = True

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
    """``(H, W)`` relative illumination ``V(r)`` of a view (see :class:`CameraEffects`).

    ``size`` is ``(W, H)``, ``principal_point`` ``(cx, cy)`` in view pixels. The
    simulator applies the same formula in a kernel; this is its reference.
    """
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
