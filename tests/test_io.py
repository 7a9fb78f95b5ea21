import contextlib

import colour
import numpy as np
import pytest

from colorps import ImageReadError, InputError, OutputError
from colorps.errors import LossyInputWarning
from colorps.io import (expand_paths, input_levels, read_image, read_stack,
                        srgb_decode, write_image)


@pytest.mark.parametrize("ext, dtype, channels, tol", [
    (".exr", "float", 5, 0.0),
    (".exr", "half", 3, 1e-3),
    (".tif", "float", 3, 0.0),
])
def test_linear_round_trip(tmp_path, rng, ext, dtype, channels, tol):
    image = rng.uniform(0, 4, (7, 9, channels)).astype(np.float32)
    names = [f"band{k}" for k in range(channels)]
    path = write_image(tmp_path / f"img{ext}", image, channel_names=names, dtype=dtype)
    back, back_names = read_image(path)
    assert back.shape == image.shape and back.dtype == np.float32
    np.testing.assert_allclose(back, image, rtol=tol, atol=tol)
    if ext == ".exr":
        assert back_names == names


@pytest.mark.parametrize("ext, dtype, step", [
    (".png", "uint8", 1 / 255), (".png", "uint16", 1 / 65535),
    (".tif", "uint8", 1 / 255), (".tif", "uint16", 1 / 65535),
    (".jpg", "uint8", 0.08),  # lossy
])
def test_integer_formats_decode_srgb(tmp_path, rng, ext, dtype, step):
    encoded = np.round(rng.uniform(0, 1, (16, 16, 3)) / step) * step
    if ext == ".jpg":
        encoded = np.full((16, 16, 3), 0.5)
    path = write_image(tmp_path / f"img{ext}", encoded, dtype=dtype)
    lossy = pytest.warns(LossyInputWarning, match="JPEG is lossy") if ext == ".jpg" else \
        contextlib.nullcontext()
    with lossy:
        linear, _ = read_image(path)
    expected = colour.cctf_decoding(encoded, function="sRGB")
    np.testing.assert_allclose(linear, expected, atol=step if ext == ".jpg" else 1e-6)
    with lossy:
        raw, _ = read_image(path, "linear")
    np.testing.assert_allclose(raw, encoded, atol=step if ext == ".jpg" else 1e-6)


def test_srgb_encoder_agrees_with_colour_science_and_keeps_shape():
    from colorps.io import srgb_encode

    values = np.linspace(-0.2, 1.3, 2 * 5 * 7, dtype=np.float32).reshape(2, 5, 7)
    expected = colour.cctf_encoding(np.clip(values, 0, 1).astype(np.float64), "sRGB")
    encoded = srgb_encode(values)
    assert encoded.shape == values.shape
    # Far below one 16-bit code (1.5e-5) and 8-bit codes land on the same integer.
    np.testing.assert_allclose(encoded, expected, atol=1e-5)
    assert np.array_equal(np.round(encoded * 255), np.round(expected * 255))
    assert srgb_encode(np.array([np.nan, 2.0])).tolist() == [0.0, 1.0]


def test_srgb_override_and_decoder(tmp_path):
    values = np.linspace(0, 1, 11, dtype=np.float32)
    np.testing.assert_allclose(srgb_decode(values), colour.cctf_decoding(values, "sRGB"),
                               rtol=1e-6)
    path = write_image(tmp_path / "f.exr", np.tile(values, (2, 1))[..., None])
    np.testing.assert_allclose(read_image(path, "srgb")[0][0, :, 0], srgb_decode(values),
                               rtol=1e-6)
    with pytest.raises(InputError, match="encoding"):
        read_image(path, "gamma")


def test_alpha_is_dropped(tmp_path, rng):
    rgba = rng.uniform(0, 1, (4, 4, 4)).astype(np.float32)
    path = write_image(tmp_path / "a.exr", rgba, channel_names=["R", "G", "B", "A"])
    image, names = read_image(path)
    assert names == ["R", "G", "B"]
    np.testing.assert_allclose(image, rgba[..., :3])


def test_stack_checks_sizes_and_channels(tmp_path):
    a = write_image(tmp_path / "a.exr", np.ones((4, 5, 3)))
    b = write_image(tmp_path / "b.exr", np.ones((4, 6, 3)))
    c = write_image(tmp_path / "c.exr", np.ones((4, 5, 1)))
    stack, _ = read_stack([a, a])
    assert stack.shape == (2, 4, 5, 3)
    with pytest.raises(ImageReadError, match=r"b.exr \(image 2 of 2 of the stack\): size "
                                              r"6x4 .* differs from image 1, .*a.exr"):
        read_stack([a, b])
    with pytest.raises(ImageReadError, match=r"c.exr \(image 2 of 2 of the stack\): .*1 channel"):
        read_stack([a, c])


def test_unreadable_files(tmp_path):
    with pytest.raises(ImageReadError, match="missing.exr: no such file"):
        read_image(tmp_path / "missing.exr")
    with pytest.raises(ImageReadError, match="is a directory"):
        read_image(tmp_path)
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(ImageReadError, match="junk.png"):
        read_image(junk)
    good = write_image(tmp_path / "good.exr", np.ones((64, 64, 3)))
    # Camera raw: refused with what to do, even when it is a readable TIFF inside.
    raw = tmp_path / "shot_01.NEF"
    raw.write_bytes(write_image(tmp_path / "t.tif", np.ones((8, 8, 3)), dtype="uint16")
                    .read_bytes())
    with pytest.raises(ImageReadError, match=r"shot_01.NEF: camera raw .*--encoding linear"):
        read_image(raw)
    cut = tmp_path / "cut.exr"
    cut.write_bytes(good.read_bytes()[:300])
    with pytest.raises(ImageReadError, match="cut.exr"):
        read_image(cut)


def test_write_is_atomic(tmp_path):
    path = write_image(tmp_path / "x.exr", np.ones((3, 3)))
    before = path.read_bytes()
    with pytest.raises(OutputError, match="x.exr: cannot write"):
        write_image(tmp_path / "x.exr", np.ones((0, 3)))  # OpenImageIO refuses
    with pytest.raises(OutputError, match="x.bogus: cannot write"):
        write_image(tmp_path / "x.bogus", np.ones((3, 3)))
    with pytest.raises(InputError, match="dtype"):
        write_image(tmp_path / "x.exr", np.ones((3, 3)), dtype="nonsense")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.exr"]  # no temporary left


@pytest.mark.parametrize("dtype, top", [("uint8", 255), ("uint16", 65535)])
def test_integer_codes_are_written_as_they_are(tmp_path, dtype, top):
    """An array of the file's integer type is written code for code; values in
    0..1 of any other type are scaled to the codes, as before."""
    import OpenImageIO as oiio

    codes = np.arange(4 * 5 * 3, dtype=dtype).reshape(4, 5, 3) * (top // 59)
    for name, image in (("codes.png", codes), ("values.png", codes / top)):
        path = write_image(tmp_path / name, image, dtype=dtype)
        file = oiio.ImageInput.open(str(path))
        stored = file.read_image(file.spec().format)
        file.close()
        assert stored.dtype == np.dtype(dtype)
        np.testing.assert_array_equal(stored, codes)


def test_expand_paths_natural_order_and_lists(tmp_path):
    for k in (1, 2, 10):
        (tmp_path / f"img{k}.exr").touch()
    with pytest.raises(ImageReadError, match="img3.exr: no such file"):
        expand_paths([str(tmp_path / "img1.exr"), str(tmp_path / "img3.exr")])
    assert [p.name for p in expand_paths(str(tmp_path / "img*.exr"))] == \
        ["img1.exr", "img2.exr", "img10.exr"]
    listing = tmp_path / "list.txt"
    listing.write_text("img10.exr\n# a comment\nimg1.exr\n")
    assert [p.name for p in expand_paths("@" + str(listing))] == ["img10.exr", "img1.exr"]
    assert len(expand_paths([str(tmp_path / "img1.exr"), str(tmp_path / "img2.exr")])) == 2
    with pytest.raises(ImageReadError, match="matches no file"):
        expand_paths(str(tmp_path / "none*.exr"))
    with pytest.raises(ImageReadError, match="cannot read list file"):
        expand_paths("@" + str(tmp_path / "nolist.txt"))


def test_input_levels_follow_bit_depth(tmp_path):
    png8 = write_image(tmp_path / "a.png", np.ones((2, 2, 3)), dtype="uint8")
    png16 = write_image(tmp_path / "b.png", np.ones((2, 2, 3)), dtype="uint16")
    exr = write_image(tmp_path / "c.exr", np.ones((2, 2, 3)))
    clip8, dark8 = input_levels(png8)
    assert clip8 == pytest.approx(colour.cctf_decoding(254.5 / 255, "sRGB"), rel=1e-5)
    assert dark8 == pytest.approx(colour.cctf_decoding(2 / 255, "sRGB"), rel=1e-5)
    assert input_levels(png8, "linear") == pytest.approx((254.5 / 255, 2 / 255), rel=1e-6)
    assert input_levels(png16)[0] > clip8 and input_levels(png16)[1] < dark8
    clip, dark = input_levels(exr)
    assert clip is None and 0 < dark < 1e-3


def test_srgb_encode_in_chunks_is_the_same(monkeypatch):
    from colorps import io

    values = np.random.default_rng(3).uniform(-0.1, 1.2, (5, 7, 3)).astype(np.float32)
    values[0, 0, 0] = np.nan
    whole = io.srgb_encode(values)
    monkeypatch.setattr(io, "SRGB_CHUNK", 7)  # chunks that split pixels' triples
    np.testing.assert_array_equal(io.srgb_encode(values), whole)
    assert whole[0, 0, 0] == 0.0 and whole.max() <= 1.0 and whole.min() >= 0.0


def test_rows_of_tiled_exr_files(tmp_path):
    """Tiled EXRs (as renderers and compositors write them) read a band of rows
    too: the row of tiles holding it, cut to the rows asked for."""
    import OpenImageIO as oiio

    rng = np.random.default_rng(2)
    image = rng.uniform(0, 1, (70, 50, 3)).astype(np.float32)
    path = write_image(tmp_path / "tiled.exr", image, tile=16)  # a partial last row
    inp = oiio.ImageInput.open(str(path))
    assert (inp.spec().tile_width, inp.spec().tile_height) == (16, 16)
    inp.close()
    assert np.array_equal(read_image(path)[0], image)
    for start, stop in [(0, 1), (15, 17), (16, 32), (20, 70), (69, 70)]:
        assert np.array_equal(read_image(path, rows=(start, stop))[0], image[start:stop])


def test_tiles_only_for_exr_files(tmp_path):
    image = np.zeros((4, 4, 3), np.float32)
    for path, tile in [(tmp_path / "a.png", 16), (tmp_path / "a.exr", 0),
                       (tmp_path / "a.exr", True)]:
        with pytest.raises(InputError, match="tile"):
            write_image(path, image, tile=tile)
        assert not path.exists()


@pytest.mark.parametrize("ext, dtype", [(".png", "uint8"), (".png", "uint16"),
                                        (".tif", "uint8"), (".tif", "uint16")])
@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_integer_files_decode_by_table_to_the_transfer_functions_values(tmp_path, rng, ext,
                                                                        dtype, encoding):
    """Every code of an 8/16-bit file is looked up in a table of decoded codes:
    the same float32 values, bit for bit, as OpenImageIO's conversion to float
    followed by colour-science's sRGB decoding, also for rows and with alpha."""
    import OpenImageIO as oiio

    image = rng.uniform(0, 1, (6, 300, 4)).astype(np.float32)
    image[0, :256, 0] = np.linspace(0, 1, 256)  # every 8-bit code
    path = write_image(tmp_path / f"f{ext}", image, dtype=dtype)
    source = oiio.ImageInput.open(str(path))
    floats = np.asarray(source.read_image(0, 0, 0, 4, "float"), np.float32)[..., :3]
    source.close()
    expected = np.asarray(colour.cctf_decoding(floats.astype(np.float64), "sRGB"),
                          np.float32) if encoding == "srgb" else floats
    decoded, names = read_image(path, encoding)
    assert decoded.dtype == np.float32 and names == ["R", "G", "B"]
    np.testing.assert_array_equal(decoded, expected)
    np.testing.assert_array_equal(read_image(path, encoding, rows=(2, 5))[0], expected[2:5])


@pytest.mark.parametrize("top", [255, 65535])
@pytest.mark.parametrize("decoded_as, encoding", [("srgb", "linear"), ("linear", "srgb")])
def test_a_stack_read_one_way_is_recoded_to_the_others_values(rng, top, decoded_as, encoding):
    """Every code's value read as one encoding becomes, bit for bit, its value
    read as the other; a value that is no code's is refused."""
    from colorps.transfer import decoding_table, recode

    codes = np.concatenate([np.arange(top + 1), rng.integers(0, top + 1, 5000)])
    stack = decoding_table(top, decoded_as)[codes].reshape(-1, 1, 1, 1)
    recode(stack, top, decoded_as, encoding)
    np.testing.assert_array_equal(stack.ravel(), decoding_table(top, encoding)[codes])
    foreign = decoding_table(top, decoded_as)[[0, 5, top]]
    foreign[1] = np.nextafter(foreign[1], np.float32(1))
    with pytest.raises(ValueError, match="1 values"):
        recode(foreign, top, decoded_as, encoding)
    with pytest.raises(ValueError, match="float32"):
        recode(np.zeros(3), top, decoded_as, encoding)


def test_stack_read_on_threads_keeps_the_order_and_names_a_bad_file(tmp_path, monkeypatch):
    from colorps import io

    monkeypatch.setattr(io, "READ_THREADS", 3)
    paths = [write_image(tmp_path / f"img_{k:02d}.png", np.full((4, 5, 3), k / 20),
                         dtype="uint16") for k in range(11)]
    stack, _ = read_stack(paths, "linear")
    np.testing.assert_allclose(stack[:, 0, 0, 0], np.arange(11) / 20, atol=1e-4)
    paths[6].write_bytes(paths[6].read_bytes()[:60])  # truncated
    with pytest.raises(ImageReadError, match="img_06.png"):
        read_stack(paths, "linear")


@pytest.mark.parametrize("pixel_type", ["uint8", "uint16", "int16"])
def test_a_stack_read_as_srgb_becomes_the_linear_read(tmp_path, rng, pixel_type):
    """gauge_check.as_linear: the stack of integer files read as sRGB (auto) is,
    bit for bit, the stack read as linear, whether recoded by table (8/16-bit)
    or read again (other integer types)."""
    import OpenImageIO as oiio

    from colorps.gauge_check import as_linear
    from colorps.io import read_info

    paths = []
    for k in range(3):
        path = tmp_path / f"img_{k}.tif"
        image = rng.uniform(0, 1, (5, 7, 3)).astype(np.float32)
        out = oiio.ImageOutput.create(str(path))
        out.open(str(path), oiio.ImageSpec(7, 5, 3, pixel_type))
        out.write_image(image)
        out.close()
        paths.append(path)
    stack, _ = read_stack(paths, "auto")
    linear, _ = read_stack(paths, "linear")
    assert not np.array_equal(stack, linear)
    np.testing.assert_array_equal(as_linear(stack, paths, read_info(paths[0]), "scene"), linear)
