"""Degradations do what they claim: measured noise, PSNR, spectra, JPEG sizes, EXIF, determinism, bit depths."""

import cv2
import numpy as np
import pytest
from PIL import Image, JpegImagePlugin

from mvrecon.cli import main
from mvrecon.errors import InputError
from mvrecon.io.images import list_images
from mvrecon.study.degrade import RECORD, Degradation, degrade_folder, degrade_image, motion_kernel, with_level

EXIF_IFD, FOCAL_LENGTH, PIXEL_X, PIXEL_Y = 0x8769, 0x920A, 0xA002, 0xA003


def texture(shape=(192, 256), seed=0, smooth=2.0, lo=40, hi=215):
    """A random textured image in [lo, hi] (no clipping when noise is added), like a real scene's detail."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), smooth)
    img = (img - img.min()) / (img.max() - img.min())
    return np.rint(lo + (hi - lo) * img).astype(np.uint8)


def white_noise(shape=(256, 256), seed=1):
    return np.random.default_rng(seed).integers(64, 192, shape).astype(np.uint8)


def write_png(path, pixels):
    assert cv2.imwrite(str(path), pixels)
    return path


def degraded(tmp_path, pixels, name="a.png", seed=0, **kw):
    src_dir, out_dir = tmp_path / "src", tmp_path / "out"
    src_dir.mkdir(exist_ok=True)
    out_dir.mkdir(exist_ok=True)
    write_png(src_dir / name, pixels)
    degrade_image(src_dir / name, out_dir / name, Degradation(**kw), seed=seed)
    return cv2.imread(str(out_dir / name), cv2.IMREAD_UNCHANGED)


def psnr(a, b, peak=255.0):
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return np.inf if mse == 0 else 10 * np.log10(peak ** 2 / mse)


def radial_power(img):
    """Power spectrum and the radial frequency (cycles/pixel) of each bin, mean removed."""
    f = np.fft.fftshift(np.fft.fft2(img.astype(float) - img.mean()))
    h, w = img.shape
    fy, fx = np.meshgrid(np.fft.fftshift(np.fft.fftfreq(h)), np.fft.fftshift(np.fft.fftfreq(w)), indexing="ij")
    return np.abs(f) ** 2, np.hypot(fx, fy), fx, fy


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0, 20.0])
def test_measured_noise_sigma_matches_request(tmp_path, sigma):
    clean = np.full((256, 256), 128, np.uint8)
    noisy = degraded(tmp_path, clean, noise_sigma=sigma)
    assert np.std(noisy.astype(float) - clean) == pytest.approx(sigma, rel=0.05)


def test_noise_sigma_is_in_8bit_grey_levels_for_16bit_images(tmp_path):
    clean = np.full((200, 200, 3), 30000, np.uint16)
    noisy = degraded(tmp_path, clean, noise_sigma=10.0)
    assert noisy.dtype == np.uint16 and noisy.shape == clean.shape
    assert np.std(noisy.astype(float) - clean) == pytest.approx(10.0 * 65535 / 255, rel=0.05)


def test_poisson_noise_variance_follows_the_signal(tmp_path):
    peak = 100.0
    for level in (64, 192):
        clean = np.full((256, 256), level, np.uint8)
        noisy = degraded(tmp_path, clean, poisson_peak=peak)
        expected = np.sqrt(level / 255 / peak) * 255  # shot noise std = sqrt(electrons) / peak, in grey levels
        assert np.std(noisy.astype(float)) == pytest.approx(expected, rel=0.05)
        assert np.mean(noisy.astype(float)) == pytest.approx(level, abs=1.0)


def test_psnr_falls_monotonically_with_sigma(tmp_path):
    clean = texture()
    values = [psnr(clean, degraded(tmp_path, clean, noise_sigma=s)) for s in (0, 2, 5, 10, 20, 40)]
    assert values[0] == np.inf
    assert all(a > b for a, b in zip(values, values[1:])), values
    # additive noise of sigma s gives PSNR 20 log10(255 / s) (clipping is avoided by the texture's range)
    assert values[3] == pytest.approx(20 * np.log10(255 / 10), abs=0.3)


def test_gaussian_blur_attenuates_frequencies_as_its_transfer_function(tmp_path):
    clean = white_noise()
    p0, f, _, _ = radial_power(clean)
    band = (f > 0.05) & (f < 0.15)
    for sigma in (1.0, 2.0):
        p1, _, _, _ = radial_power(degraded(tmp_path, clean, blur_sigma=sigma))
        measured = p1[band].sum() / p0[band].sum()
        predicted = np.sum(p0[band] * np.exp(-4 * np.pi ** 2 * sigma ** 2 * f[band] ** 2)) / p0[band].sum()
        assert measured == pytest.approx(predicted, rel=0.12)
    high = f > 0.25
    energies = [radial_power(degraded(tmp_path, clean, blur_sigma=s))[0][high].sum() for s in (0, 0.5, 1, 2, 4)]
    assert all(a > b for a, b in zip(energies, energies[1:])), energies


@pytest.mark.parametrize("angle, along, across", [(0.0, "x", "y"), (90.0, "y", "x")])
def test_motion_blur_smears_only_along_its_direction(tmp_path, angle, along, across):
    clean = white_noise()
    p0, _, fx, fy = radial_power(clean)
    p1, _, _, _ = radial_power(degraded(tmp_path, clean, motion_length=9.0, motion_angle=angle))
    freq = {"x": fx, "y": fy}
    on_along_axis = (np.abs(freq[across]) < 1e-9) & (np.abs(freq[along]) > 0.2)
    on_across_axis = (np.abs(freq[along]) < 1e-9) & (np.abs(freq[across]) > 0.2)
    assert p1[on_along_axis].sum() / p0[on_along_axis].sum() < 0.05  # high frequencies along the motion vanish
    assert p1[on_across_axis].sum() / p0[on_across_axis].sum() == pytest.approx(1.0, rel=0.1)  # across: kept


@pytest.mark.parametrize("length, angle", [(9.0, 0.0), (12.0, 30.0), (5.0, 90.0)])
def test_motion_kernel_is_a_normalised_line_of_the_asked_length_and_angle(length, angle):
    k = motion_kernel(length, angle).astype(float)
    assert k.sum() == pytest.approx(1.0)
    ys, xs = np.mgrid[: k.shape[0], : k.shape[1]]
    c = k.shape[0] // 2
    a = np.deg2rad(angle)
    along = (xs - c) * np.cos(a) - (ys - c) * np.sin(a)  # image y points down, angles are counter-clockwise
    across = (xs - c) * np.sin(a) + (ys - c) * np.cos(a)
    assert np.sum(k * along) == pytest.approx(0.0, abs=1e-4)
    # the variance of a uniform segment, plus 1/6 px^2 from the bilinear splat that anti-aliases it
    assert np.sum(k * along ** 2) == pytest.approx(length ** 2 / 12 + 1 / 6, rel=0.03)
    assert np.sum(k * across ** 2) < 0.3  # only the sub-pixel splat spreads it sideways


def test_sharpening_raises_high_frequency_energy(tmp_path):
    clean = texture(smooth=1.0)
    p0, f, _, _ = radial_power(clean)
    high = f > 0.15
    gains = [radial_power(degraded(tmp_path, clean, sharpen_amount=a))[0][high].sum() / p0[high].sum()
             for a in (0.5, 1.0, 2.0)]
    assert 1.2 < gains[0] < gains[1] < gains[2], gains


def test_downscale_gamma_and_brightness_map_values_as_stated(tmp_path):
    clean = texture(shape=(200, 300))
    small = degraded(tmp_path, clean, downscale=2.0)
    assert small.shape == (100, 150)
    assert np.abs(small.astype(float) - cv2.resize(clean, (150, 100), interpolation=cv2.INTER_AREA)).max() <= 1
    flat = np.full((32, 32), 128, np.uint8)
    assert degraded(tmp_path, flat, gamma=2.0)[0, 0] == round(255 * (128 / 255) ** 2)
    assert degraded(tmp_path, flat, brightness=1.5)[0, 0] == 192
    assert degraded(tmp_path, flat, brightness=3.0)[0, 0] == 255  # clipped like a saturated sensor


def test_degradations_compose_in_the_stated_order(tmp_path):
    """Noise comes after blur: the noise in the output is not blurred (blurring it first would shrink it)."""
    clean = texture()
    out = degraded(tmp_path, clean, blur_sigma=2.0, noise_sigma=10.0)
    blurred = cv2.GaussianBlur(clean.astype(np.float32), (0, 0), 2.0, borderType=cv2.BORDER_REFLECT_101)
    assert np.std(out.astype(float) - blurred) == pytest.approx(10.0, rel=0.05)


def test_jpeg_file_size_falls_with_quality(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    rgb = np.dstack([texture(seed=s, smooth=1.0) for s in range(3)])
    Image.fromarray(rgb).save(src / "v.jpg", quality=98)
    sizes, errors = [], []
    for q in (95, 75, 50, 25, 10):
        out = tmp_path / f"q{q}"
        degrade_folder(src, out, Degradation(jpeg_quality=q))
        sizes.append((out / "v.jpg").stat().st_size)
        errors.append(-psnr(rgb, np.asarray(Image.open(out / "v.jpg"))))
    assert all(a > b for a, b in zip(sizes, sizes[1:])), sizes
    assert all(a < b for a, b in zip(errors, errors[1:])), errors


def test_jpeg_artefacts_are_kept_in_lossless_outputs(tmp_path):
    clean = texture()
    values = [psnr(clean, degraded(tmp_path, clean, jpeg_quality=q)) for q in (95, 50, 10)]
    assert all(a > b for a, b in zip(values, values[1:])) and values[0] < np.inf


def exif_block(width, height):
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "mvrecon-test", "cam-1"
    exif.get_ifd(EXIF_IFD).update({FOCAL_LENGTH: 4.5, PIXEL_X: width, PIXEL_Y: height})
    return exif


@pytest.mark.parametrize("suffix", [".jpg", ".png", ".tif"])
def test_names_and_exif_survive(tmp_path, suffix):
    src = tmp_path / "src"
    src.mkdir()
    rgb = np.dstack([texture(seed=s) for s in range(3)])
    names = [f"img_{k:02d}{suffix}" for k in range(3)]
    for name in names:
        Image.fromarray(rgb).save(src / name, exif=exif_block(256, 192))
    out = tmp_path / "out"
    assert main(["degrade", "-q", str(src), "-o", str(out), "--noise", "5", "--downscale", "2"]) == 0
    assert sorted(p.name for p in out.iterdir() if p.name != RECORD) == names
    for name in names:
        with Image.open(out / name) as im:
            assert im.size == (128, 96)
            exif = im.getexif()
            assert exif[0x010F] == "mvrecon-test" and exif[0x0110] == "cam-1"
            if suffix != ".tif":  # TIFF keeps its base tags; the EXIF sub-IFD is a JPEG/PNG block feature
                sub = exif.get_ifd(EXIF_IFD)
                assert float(sub[FOCAL_LENGTH]) == 4.5 and (sub[PIXEL_X], sub[PIXEL_Y]) == (128, 96)


def test_exif_block_is_byte_identical_when_the_size_is_unchanged(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    Image.fromarray(texture()).save(src / "g.png", exif=exif_block(256, 192))
    degrade_folder(src, tmp_path / "out", Degradation(noise_sigma=3, blur_sigma=1))
    before, after = Image.open(src / "g.png").info["exif"], Image.open(tmp_path / "out" / "g.png").info["exif"]
    assert before == after


def test_same_seed_gives_same_bytes_and_file_order_does_not_matter(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for k in range(3):
        write_png(src / f"{k}.png", np.dstack([texture(seed=k + s) for s in range(3)]))
    deg = Degradation(noise_sigma=8, poisson_peak=200, blur_sigma=0.7, jpeg_quality=60)
    a, b, c = (degrade_folder(src, tmp_path / d, deg, seed=s) for d, s in (("a", 1), ("b", 1), ("c", 2)))
    single = tmp_path / "single"
    single.mkdir()
    degrade_image(src / "2.png", single / "2.png", deg, seed=1)  # alone, not third in a folder
    for pa, pb, pc in zip(a, b, c):
        assert pa.read_bytes() == pb.read_bytes() != pc.read_bytes()
    assert (single / "2.png").read_bytes() == (tmp_path / "a" / "2.png").read_bytes()
    assert a[0].read_bytes() != a[1].read_bytes()


def test_grey_16bit_and_alpha_layouts_are_kept(tmp_path):
    grey16 = (texture().astype(np.uint16) * 257)
    out = degraded(tmp_path, grey16, name="g16.png", noise_sigma=4, blur_sigma=1)
    assert out.dtype == np.uint16 and out.shape == grey16.shape
    assert 4 * 257 * 0.8 < np.std(out.astype(float) - grey16) < 4 * 257 * 1.5
    rgba = np.dstack([texture(seed=s) for s in range(3)] + [np.full((192, 256), 77, np.uint8)])
    out = degraded(tmp_path, rgba, name="rgba.png", noise_sigma=10)
    assert out.shape == rgba.shape and (out[..., 3] == 77).all() and not (out[..., :3] == rgba[..., :3]).all()
    grey8 = texture()
    out = degraded(tmp_path, grey8, name="g8.png", jpeg_quality=50, downscale=2)
    assert out.dtype == np.uint8 and out.shape == (96, 128)
    for name, pixels in (("g16.tif", grey16), ("c16.tif", np.dstack([grey16] * 3))):
        out = degraded(tmp_path, pixels, name=name, noise_sigma=2)
        assert out.dtype == np.uint16 and out.shape == pixels.shape
        assert np.std(out.astype(float) - pixels) == pytest.approx(2 * 257, rel=0.05)


def test_no_degradation_copies_the_bytes(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    write_png(src / "x.png", texture())
    degrade_folder(src, tmp_path / "out", Degradation())
    assert (src / "x.png").read_bytes() == (tmp_path / "out" / "x.png").read_bytes()


def test_bad_input_is_one_line_and_exit_code_2(tmp_path, capsys, caplog):
    src = tmp_path / "src"
    src.mkdir()
    assert main(["degrade", "-q", str(src), "-o", str(tmp_path / "o")]) == 2
    assert "no readable JPEG, PNG, TIFF, BMP or PNM images found" in capsys.readouterr().err
    write_png(src / "x.png", texture())
    assert main(["degrade", "-q", str(src), "-o", str(tmp_path / "o"), "--jpeg", "150"]) == 2
    assert "JPEG quality must be 1..100" in capsys.readouterr().err
    assert main(["degrade", "-q", str(src), "-o", str(src), "--noise", "3"]) == 2
    assert "must differ from the input folder" in capsys.readouterr().err
    # unreadable files are left out with a reason, as `reconstruct` leaves them out; the others are degraded
    (src / "bad.png").write_bytes(b"not a png")
    assert cv2.imwrite(str(tmp_path / "whole.jpg"), np.dstack([texture()] * 3))
    whole = (tmp_path / "whole.jpg").read_bytes()
    (src / "cut.jpg").write_bytes(whole[: len(whole) // 2])  # cv2.imread would fill its lower half with grey
    with caplog.at_level("WARNING"):  # the listing `reconstruct` uses says why, once per file
        assert main(["degrade", "-q", str(src), "-o", str(tmp_path / "o"), "--noise", "3"]) == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert [m for m in warned if "bad.png" in m] == [f"skipping {src / 'bad.png'}: {list_images(src)[1]['bad.png']}"]
    assert len([m for m in warned if "cut.jpg" in m]) == 1 and "cut.jpg" in list_images(src)[1]
    assert sorted(p.name for p in (tmp_path / "o").iterdir() if p.name != RECORD) == ["x.png"]
    (src / "x.png").unlink()
    assert main(["degrade", "-q", str(src), "-o", str(tmp_path / "o2"), "--noise", "3"]) == 2
    assert "no readable JPEG, PNG, TIFF, BMP or PNM images found (2 file(s) skipped)" in capsys.readouterr().err


@pytest.mark.parametrize("options, message", [
    # the flag and the value the user typed
    (["--noise=-5"], "--noise -5: noise sigma must be >= 0"),
    (["--jpeg", "150"], "--jpeg 150: JPEG quality must be 1..100 (0 = off)"),
    (["--downscale", "0.5"], "--downscale 0.5: downscale factor must be >= 1"),
    (["--sharpen", "1", "--sharpen-radius", "0"], "--sharpen-radius 0: sharpen radius must be > 0"),
    (["--blur", "inf"], "--blur inf: blur sigma must be a finite number"),
    (["--motion", "inf"], "--motion inf: motion blur length must be a finite number"),
    (["--poisson", "inf"], "--poisson inf: Poisson peak must be a finite number"),
    (["--poisson", "1e300"], "--poisson 1e+300: Poisson peak must be at most 1e+12 (the noise is far below one grey "
                             "level there)"),
    (["--motion-angle", "nan", "--motion", "5"], "--motion-angle nan: motion angle must be a finite number"),
    # kernels must fit in the image (192 px high): --motion 1e9 ran out of memory, --blur 1e5 ran for minutes
    (["--motion", "1e9"], "{src}: --motion 1e+09 is too large for its 256x192 pixels (at most 191: the kernel must "
                          "fit in the image)"),
    (["--blur", "1e5"], "{src}: --blur 100000 is too large for its 256x192 pixels (at most 23.875: the kernel must "
                        "fit in the image)"),
    (["--downscale", "2", "--blur", "12"], "{src}: --blur 12 is too large for its 128x96 pixels (at most 11.875: "
                                           "the kernel must fit in the image)"),
    (["--sharpen", "1", "--sharpen-radius", "1e4"], "{src}: --sharpen-radius 10000 is too large for its 256x192 "
                                                    "pixels (at most 23.875: the kernel must fit in the image)"),
])
def test_impossible_settings_are_one_line_errors(tmp_path, capsys, options, message):
    src = tmp_path / "src"
    src.mkdir()
    write_png(src / "a.png", texture())
    assert main(["degrade", "-q", str(src), "-o", str(tmp_path / "out"), *options]) == 2
    assert capsys.readouterr().err == f"mvrecon: error: {message.format(src=src / 'a.png')}\n"
    assert not (tmp_path / "out" / "a.png").exists()
    with pytest.raises(InputError, match="^--jpeg inf: JPEG quality must be a finite number$"):
        with_level(Degradation(), "jpeg_quality", float("inf"))  # a study level


def test_rerun_continues_after_an_interruption(tmp_path, capsys, monkeypatch):
    import mvrecon.study.degrade as degrade

    src, out = tmp_path / "src", tmp_path / "out"
    src.mkdir()
    for k in range(3):
        write_png(src / f"{k}.png", texture(seed=k))
    written, write = [], degrade._write

    def recorded(path, *args):
        written.append(path)
        write(path, *args)

    def interrupted_at_the_second(path, *args):
        if written:
            path.write_bytes(b"cut off")  # a partial file, then Ctrl-C
            raise KeyboardInterrupt
        recorded(path, *args)

    monkeypatch.setattr(degrade, "_write", interrupted_at_the_second)
    argv = ["degrade", "-q", str(src), "-o", str(out), "--noise", "5"]
    assert main(argv) == 130
    assert "rerun the same command to continue" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [RECORD, "0.png"]  # nothing cut off under any name
    first = (out / "0.png").stat().st_mtime_ns
    written.clear()
    monkeypatch.setattr(degrade, "_write", recorded)
    assert main(argv) == 0
    assert len(written) == 2 and (out / "0.png").stat().st_mtime_ns == first  # 1.png and 2.png only
    assert sorted(p.name for p in out.iterdir()) == [RECORD, "0.png", "1.png", "2.png"]
    whole = degrade_folder(src, tmp_path / "whole", Degradation(noise_sigma=5))  # uninterrupted: the same bytes
    assert [p.read_bytes() for p in whole] == [(out / p.name).read_bytes() for p in whole]
    assert main(["degrade", "-q", str(src), "-o", str(out), "--noise", "6"]) == 2  # not mixed with noise 5
    assert capsys.readouterr().err.startswith(f"mvrecon: error: {out}: written earlier with another degradation")


def test_sub_folders_are_searched_and_kept_as_reconstruct_lists_them(tmp_path, capsys):
    """The images `reconstruct` takes (io.images.list_images), under the same relative paths: a folder with
    images only in sub-folders was refused ("no JPEG, PNG or TIFF images here")."""
    src = tmp_path / "src"
    same = texture()
    for name in ("a/0.png", "a/1.png", "b/0.png", "b/deeper/2.png", "run/3.png", ".hidden/4.png"):
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        write_png(src / name, same)
    (src / "run" / "database.db").write_bytes(b"")  # a run's outputs: not images
    (src / "notes.txt").write_text("not an image")
    out = tmp_path / "out"
    assert main(["degrade", "-q", str(src), "-o", str(out), "--noise", "5"]) == 0
    names = list_images(src)[0]
    assert names == ["a/0.png", "a/1.png", "b/0.png", "b/deeper/2.png"]
    assert list_images(out)[0] == names
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == sorted(names + [RECORD])
    a, b = (cv2.imread(str(out / n), cv2.IMREAD_UNCHANGED).astype(float) for n in ("a/0.png", "b/0.png"))
    assert np.std(a - same) == pytest.approx(5.0, rel=0.05) and np.std(a - b) > 5.0  # each its own noise
    # the output folder may neither sit inside the input folder (its copies would be listed as images) nor hold it
    assert main(["degrade", "-q", str(src), "-o", str(src / "noisy"), "--noise", "5"]) == 2
    assert "inside the input folder" in capsys.readouterr().err and not (src / "noisy").exists()
    assert main(["degrade", "-q", str(src / "a"), "-o", str(src), "--noise", "5"]) == 2
    assert "holds the input folder" in capsys.readouterr().err


def test_noise_on_a_jpeg_input_keeps_its_colour_and_jpeg_quality_is_unchanged(tmp_path):
    """A JPEG input re-encoded after --noise keeps the noise of each colour channel (4:4:4, quality 100: the
    default 4:2:0 averaged it to a std of 7.1 for sigma 10); --jpeg Q stays Pillow's encoding at quality Q."""
    src = tmp_path / "src"
    src.mkdir()
    rgb = np.zeros((192, 256, 3), np.uint8) + np.array([128, 100, 160], np.uint8)
    Image.fromarray(rgb).save(src / "c.jpg", quality=95)
    clean = np.asarray(Image.open(src / "c.jpg")).astype(float)
    degrade_folder(src, tmp_path / "noisy", Degradation(noise_sigma=10))
    with Image.open(tmp_path / "noisy" / "c.jpg") as im:
        noisy, sampling = np.asarray(im).astype(float), JpegImagePlugin.get_sampling(im)
    assert [np.std(noisy[..., c] - clean[..., c]) for c in range(3)] == pytest.approx([10.0] * 3, rel=0.05)
    assert sampling == 0  # 4:4:4
    degrade_folder(src, tmp_path / "q50", Degradation(jpeg_quality=50))
    Image.fromarray(np.asarray(Image.open(src / "c.jpg"))).save(tmp_path / "pillow50.jpg", quality=50)
    with Image.open(tmp_path / "q50" / "c.jpg") as im, Image.open(tmp_path / "pillow50.jpg") as ref:
        assert JpegImagePlugin.get_sampling(im) == JpegImagePlugin.get_sampling(ref) == 2  # 4:2:0
        assert im.quantization == ref.quantization
    assert (tmp_path / "q50" / "c.jpg").read_bytes() == (tmp_path / "pillow50.jpg").read_bytes()
