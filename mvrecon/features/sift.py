"""SIFT keypoints and descriptors with OpenCV, in COLMAP's conventions.

`extract_sift(image, config) -> (keypoints, descriptors)`:
- `image`: any array `read_image` returns (grey or RGB, 8 or 16 bit);
- `keypoints`: (N,4) float32 x, y, scale, orientation. x, y are in COLMAP's pixel convention (top-left pixel
  centre at (0.5, 0.5): subtract 0.5 for OpenCV drawing/geometry); scale is the blob's sigma in full-resolution
  pixels (OpenCV's `size` / 2); orientation is OpenCV's angle in radians;
- `descriptors`: (N,128) uint8, L2-unit (or RootSIFT) vectors scaled by 512 and clipped at 255, as COLMAP stores
  them, so `descriptors / 512` is (nearly) unit length.

With `min_num_features`, an image with fewer keypoints keeps the strongest of half the peak threshold up to that
many (`_detect_topped_up`), so that weakly textured images are not matched on a few hundred keypoints.

Images larger than `max_image_size` on their long side are shrunk first (SIFT on a 6000 px photo costs a lot and
finds mostly noise-scale blobs) and the keypoints are mapped back to full-resolution coordinates.
"""

from dataclasses import dataclass

import numpy as np

from ..config import bounded
from ..io.images import to_gray


@dataclass(frozen=True)
class SiftConfig:
    max_num_features: int = bounded(8192, 1)  # beyond it, keep the coarsest scales (`_capped`)
    max_image_size: int = bounded(3200, 16)  # long side in pixels before detection; keypoints are mapped back
    # smallest |DoG| at the interpolated extremum, on [0,1] intensities: COLMAP's (VLFeat's) peak_threshold.
    # The default is twice COLMAP's 0.02 / 3: COLMAP's finds 1.2-3.4x the keypoints where the 8192 cap is not
    # reached, so the front end takes 1.1-4.1x as long; it raises AUC@1 on 18 of 20 sets with ground truth and
    # lowers it on imc_reichstag and fisheye_orbit_small (docs/benchmarks.md, "Keypoints topped up")
    peak_threshold: float = bounded(0.04 / 3, 0.0, low_open=True)
    # an image with fewer keypoints than this at peak_threshold keeps the strongest of half of it (COLMAP's) up
    # to this many, those of peak_threshold among them: weakly textured images gain keypoints where matching them
    # costs little, and the others keep theirs. Off (0) by default: at 2000 AUC@1 rose on 12 of the 13 sets it
    # touched with our incremental mapper, but the global mapper lost imc_reichstag and facade_bricks_small, and
    # the mapper suite failed 4 rows (docs/benchmarks.md, "Keypoints topped up")
    min_num_features: int = bounded(0, 0)
    # reject edge-like responses (ratio of principal curvatures)
    edge_threshold: float = bounded(10.0, 0.0, low_open=True)
    num_octave_layers: int = bounded(3, 1)  # DoG layers per octave
    upright: bool = False  # all orientations 0 (faster, better when the camera never rolls)
    root_sift: bool = True  # RootSIFT (L1 normalise, square root): better matching, COLMAP's default
    # OpenCV's upsampling of the first octave (resize) puts every keypoint a constant 0.25 px right of and
    # below the blob, at all scales; `extract_sift` corrects that, which raised AUC@1 from 0.938 to 0.966 on
    # the room scene and from 0.951 to 0.972 on planar (the principal point stays at the image centre, so the
    # shift was a model error). precise_upscale (exact 2x, OpenCV's enable_precise_upscale) needs no
    # correction but finds other features: worse on imc_reichstag (AUC@5 0.54-0.62 over 4 seeds) and
    # wide_orbit, so it is off (docs/frontend.md)
    precise_upscale: bool = False


def extract_sift(image: np.ndarray, config: SiftConfig = SiftConfig(), reduced: int = 1
                 ) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on an image array: (N,4) keypoints in full-resolution COLMAP pixels, (N,128) uint8 descriptors.
    `reduced`: the image is the photo decoded at 1/reduced of its size (io.images.read_image_for_detection);
    it is detected at the size the full photo would be, and the keypoints are given in the full photo's
    pixels."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    gray = to_gray(image)
    h, w = gray.shape[0] * reduced, gray.shape[1] * reduced
    factor = min(1.0, config.max_image_size / max(h, w))
    if factor < 1.0:
        size = (max(1, round(w * factor)), max(1, round(h * factor)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    sx, sy = w / gray.shape[1], h / gray.shape[0]
    kps, desc = _detect_topped_up(gray, config)
    if not kps or desc is None:
        return np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8)
    keypoints = np.array([(k.pt[0], k.pt[1], k.size, k.angle) for k in kps], dtype=np.float64)
    # OpenCV pixel centre (0,0) -> COLMAP (0.5,0.5), less the 0.25 px shift of OpenCV's upsampling; full size
    shift = 0.5 if config.precise_upscale else 0.25
    keypoints[:, 0] = (keypoints[:, 0] + shift) * sx
    keypoints[:, 1] = (keypoints[:, 1] + shift) * sy
    keypoints[:, 2] *= 0.5 * (sx + sy) / 2
    keypoints[:, 3] = np.radians(keypoints[:, 3])
    return keypoints.astype(np.float32), descriptors_to_uint8(desc, root=config.root_sift)


# whether the last image this process extracted was topped up: the next one most likely is too (a set's images
# are alike), and then one detection at the lower threshold costs less than two
_last_topped_up = False


def _detect_topped_up(gray: np.ndarray, config: SiftConfig) -> tuple:
    """OpenCV's keypoints and descriptors at peak_threshold; for fewer than min_num_features, the strongest of
    half the threshold up to that many, capped at max_num_features.

    A detection at half the threshold holds every keypoint of peak_threshold, found and refined alike, with the same
    descriptors (OpenCV's response is the refined |DoG| it compares with the threshold), so its keypoints that
    reach peak_threshold are the detection at peak_threshold. The result is the same whichever detection runs first;
    `_last_topped_up` only chooses the one likely to be enough."""
    global _last_topped_up
    wanted = min(config.min_num_features, config.max_num_features)
    if not (wanted and _last_topped_up):
        kps, desc = _detect(gray, config, config.peak_threshold)
        _last_topped_up = len(kps) < wanted
        if not _last_topped_up:
            return kps, desc
    kps, desc = _detect(gray, config, config.peak_threshold / 2, capped=False)
    responses = np.array([k.response for k in kps], np.float32)
    # OpenCV's own test, in its precision: |DoG| x layers against contrastThreshold
    reaching = responses * np.float32(config.num_octave_layers) >= config.peak_threshold * config.num_octave_layers
    _last_topped_up = int(reaching.sum()) < wanted
    keep = np.nonzero(reaching)[0] if not _last_topped_up else \
        np.sort(np.argsort(-responses, kind="stable")[:wanted])
    kps, desc = _subset(kps, desc, keep)
    return _subset(kps, desc, _capped(kps, config))


def _detect(gray: np.ndarray, config: SiftConfig, peak_threshold: float, capped: bool = True) -> tuple:
    """OpenCV's keypoints and descriptors of `gray` at `peak_threshold`, capped at max_num_features unless
    `capped` is False."""
    import cv2  # noqa: PLC0415 - loaded after the feature workers fork (executor._get_context)

    # OpenCV keeps an extremum whose interpolated |DoG| reaches contrastThreshold / nOctaveLayers (after a
    # pre-filter at half that), the test VLFeat/COLMAP make with peak_threshold
    sift = cv2.SIFT_create(nfeatures=0, nOctaveLayers=config.num_octave_layers,
                           contrastThreshold=peak_threshold * config.num_octave_layers,
                           edgeThreshold=config.edge_threshold, enable_precise_upscale=config.precise_upscale)
    if config.upright:
        kps = sift.detect(gray, None)
        unique = {}
        for kp in kps:  # OpenCV duplicates a blob for each dominant orientation; upright needs it once
            unique.setdefault((round(kp.pt[0], 2), round(kp.pt[1], 2), round(kp.size, 2)), kp)
        kps = [cv2.KeyPoint(k.pt[0], k.pt[1], k.size, 0.0, k.response, k.octave, k.class_id)
               for k in unique.values()]
        kps = [kps[i] for i in _capped(kps, config)] if capped else kps
        return sift.compute(gray, kps) if kps else ((), None)
    # describing the keypoints dropped below costs about what detecting first and building a second pyramid
    # for the kept ones does (docs/frontend.md, "Feature cap")
    kps, desc = sift.detectAndCompute(gray, None)
    return _subset(kps, desc, _capped(kps, config)) if capped else (kps, desc)


def _subset(kps, desc, keep: np.ndarray) -> tuple:
    """The keypoints and descriptor rows at the indices `keep`; all of them, as they are, when it keeps all."""
    if len(keep) == len(kps):
        return kps, desc
    return [kps[i] for i in keep], (desc[keep] if desc is not None else None)


def extraction_memory_mb(width: int, height: int, config: SiftConfig = SiftConfig(),
                         reduced: int = 1) -> float:
    """The memory (MB) a process needs to extract a `width` x `height` image decoded at 1/`reduced` of its
    size: its scale space at the detection size, float32 on an upsampled first octave (num_octave_layers + 3
    Gaussian and + 2 DoG levels, 4/3 of it over all octaves: 235 bytes a detection pixel at 3 layers), and 4
    bytes a decoded pixel (RGB and its grey copy). A worker's peak over its memory before the image, measured
    at the default settings: 179 MB for 1000 x 750 (this gives 171), 693 MB for 2000 x 1500 (683), 1,550 MB
    for 3000 x 2250 (1,536), 1,774 MB for 4000 x 3000 (1,765), 1,816 MB for 12000 x 9000 decoded at 1/2
    (1,822)."""
    if width <= 0 or height <= 0:
        return 0.0
    factor = min(1.0, config.max_image_size / max(width, height))
    detected = round(width * factor) * round(height * factor)
    scale_space = 4 * 4 * detected * (2 * config.num_octave_layers + 5) * 4 / 3
    return (scale_space + 4 * width * height / reduced ** 2) / 2 ** 20


def _capped(kps, config: SiftConfig) -> np.ndarray:
    """Indices (in detection order) of the max_num_features keypoints of the coarsest DoG levels, the
    strongest within the last level kept.

    COLMAP caps features the same way (coarse levels first), where OpenCV's `nfeatures` keeps the strongest
    responses, two thirds of them from the two finest levels on large photos (they repeat poorly across views):
    full-size Sceaux castle lost an image with those (docs/frontend.md, "Feature cap")."""
    if len(kps) <= config.max_num_features:
        return np.arange(len(kps))
    octave = np.array([k.octave for k in kps], dtype=np.int64)
    # OpenCV packs a signed octave in the low byte and the layer in the next one
    level = (((octave & 255) ^ 128) - 128) * config.num_octave_layers + ((octave >> 8) & 255)
    order = np.lexsort((-np.array([k.response for k in kps]), -level))
    return np.sort(order[:config.max_num_features])


def descriptors_to_uint8(desc: np.ndarray, root: bool) -> np.ndarray:
    """COLMAP's storage: unit vectors (L2, or RootSIFT) * 512, clipped to 255, as uint8."""
    d = np.asarray(desc, dtype=np.float32)
    if root:
        d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))
    else:
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.clip(np.round(d * 512.0), 0, 255).astype(np.uint8)

