import io
import json
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from pwlreg.core.errors import ImageTooLargeError, InputError, UnsupportedMediaError
from pwlreg.core.io import encode_png, load_points, probe_image, read_image


def test_points_json_and_csv_agree():
    doc = {"reference": [[1, 2], [3.5, 4]], "moving": [[5, 6], [7, 8.25]]}
    r1, m1 = load_points(json.dumps(doc).encode())
    r2, m2 = load_points("x,y,x_moving,y_moving\n1,2,5,6\n3.5,4,7,8.25\n")
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(m1, m2)
    assert r1.shape == (2, 2)


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "empty"),
        ("{not json", "not valid JSON"),
        ('{"reference": [[1, 2]]}', "reference"),
        ('{"reference": [[1, 2]], "moving": [[1, 2], [3, 4]]}', "1 reference points but 2"),
        ('{"reference": [[1, 2, 3]], "moving": [[1, 2, 3]]}', r"\[x, y\] pairs"),
        ("a,b\n1,2\n", "header"),
        ("\x00\r\x00", "CSV"),
        ("x,y,x_moving,y_moving\n1,2,3\n", "four numbers"),
        ('{"reference": [[1, NaN]], "moving": [[1, 2]]}', "non-finite"),
        ('{"reference": [["1", "2"]], "moving": [[1, 2]]}', "numbers"),
        ('{"reference": [[true, false]], "moving": [[1, 2]]}', "numbers"),
        ('{"reference": [[1' + "0" * 400 + ', 2]], "moving": [[5, 6]]}', "numbers"),
        ('{"reference": ' + "[" * 100000 + "]" * 100000 + ', "moving": []}', "nested"),
    ],
)
def test_bad_points_are_clear_errors(text, match):
    with pytest.raises(InputError, match=match):
        load_points(text)


def test_read_image_round_trip_and_limits():
    img = (np.arange(12 * 10, dtype=np.uint16).reshape(10, 12) * 500).astype(np.uint16)
    data = encode_png(img)
    back = read_image(data)
    np.testing.assert_array_equal(back, img)
    with pytest.raises(ImageTooLargeError, match="more than the limit"):
        read_image(data, max_pixels=100)
    with pytest.raises(UnsupportedMediaError):
        read_image(b"definitely not an image")
    with pytest.raises(UnsupportedMediaError):
        read_image(b"")
    truncated = cv2.imencode(".png", np.zeros((50, 50), np.uint8))[1].tobytes()[:60]
    with pytest.raises(UnsupportedMediaError):
        read_image(truncated)


def test_bom_in_text_points():
    ref, mov = load_points("\ufeffx,y,x_moving,y_moving\n1,2,3,4\n")
    assert ref.tolist() == [[1, 2]] and mov.tolist() == [[3, 4]]


def test_decompression_bomb_refused_before_decoding():
    # A PNG header claiming 100000 x 100000 pixels with almost no data.
    big = np.zeros((1, 1), np.uint8)
    data = bytearray(cv2.imencode(".png", big)[1].tobytes())
    data[16:24] = (100000).to_bytes(4, "big") + (100000).to_bytes(4, "big")
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")  # keep the IHDR valid
    with pytest.raises(ImageTooLargeError):
        read_image(bytes(data), max_pixels=50_000_000)
    # Without a limit of its own the decoder's limit (2**30 pixels) still applies, cleanly.
    with pytest.raises(ImageTooLargeError):
        read_image(bytes(data))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("threads", [1, 3])
def test_png_round_trip(dtype, channels, threads):
    rng = np.random.default_rng(channels)
    for shape in [(1, 1), (1, 7), (9, 1), (650, 517)]:  # the last one is split into 3 pieces
        img = rng.integers(0, np.iinfo(dtype).max, shape + (channels,), dtype=dtype)
        img = img[:, :, 0] if channels == 1 else img
        data = encode_png(img, threads=threads)
        back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        # OpenCV reads grey+alpha as BGRA.
        expected = np.dstack([img[:, :, 0]] * 3 + [img[:, :, 1]]) if channels == 2 else img
        assert back.dtype == dtype
        np.testing.assert_array_equal(back, expected)
        if dtype == np.uint8:  # an independent decoder; Pillow reads 16-bit colour as 8-bit
            rgb = img[:, :, [2, 1, 0, 3][:channels]] if channels >= 3 else img
            np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(data))), rgb)


@pytest.mark.parametrize("threads", [1, 2])
def test_png_in_many_blocks_and_pieces_of_a_strided_image(monkeypatch, threads):
    # Small blocks and pieces, as a huge image would have them; a view with negative strides.
    monkeypatch.setattr("pwlreg.core.formats.png._BLOCK_BYTES", 1000)
    monkeypatch.setattr("pwlreg.core.formats.png._PIECE_BYTES", 300 * 1024)
    monkeypatch.setattr("pwlreg.core.formats.png._STRIP_BYTES", 1 << 20)
    base = np.random.default_rng(1).integers(0, 65535, (700, 900, 4), dtype=np.uint16)
    img = base[::-1, 100:, :]
    data = encode_png(img, threads=threads)
    assert data.count(b"IDAT") >= 5
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, img)


def test_png_of_a_smooth_image_is_smaller_than_opencv_default():
    y, x = np.mgrid[0:300, 0:400]
    img = (127 + 60 * np.sin(x / 17.0) * np.cos(y / 23.0)).astype(np.uint8)
    ours = encode_png(np.dstack([img, np.full_like(img, 255)]))
    opencv = cv2.imencode(".png", np.dstack([img, img, img, np.full_like(img, 255)]))[1]
    assert len(ours) < len(opencv) / 2


def _damage_idat(png: bytes, fix_crc: bool) -> bytes:
    """Flip bytes inside the first IDAT chunk's data, keeping its CRC right or not."""
    data = bytearray(png)
    at = data.index(b"IDAT")
    length = int.from_bytes(data[at - 4:at], "big")
    for i in range(at + 4 + 2, at + 4 + min(length, 40)):
        data[i] ^= 0x5A
    if fix_crc:
        crc = zlib.crc32(bytes(data[at:at + 4 + length]))
        data[at + 4 + length:at + 8 + length] = crc.to_bytes(4, "big")
    return bytes(data)


@pytest.mark.parametrize(
    "image, ext, match",
    [
        (np.zeros((1, 50), np.uint8), ".png", "too small"),
        (np.zeros((1, 50), np.uint8), ".tiff", "too small"),
    ],
)
def test_probe_refuses_what_decoding_would_refuse(image, ext, match):
    data = cv2.imencode(ext, image)[1].tobytes()
    for check in (probe_image, read_image):
        with pytest.raises(InputError, match=match):
            check(data)


@pytest.mark.parametrize("dtype", [np.float32, np.int32, np.int16])
def test_tiffs_of_other_sample_types_are_rasters(dtype):
    image = np.arange(30, dtype=dtype).reshape(5, 6)
    data = cv2.imencode(".tiff", image)[1].tobytes()
    assert probe_image(data) == (6, 5)
    raster = read_image(data)
    assert isinstance(raster, np.ma.MaskedArray) and raster.dtype == dtype
    np.testing.assert_array_equal(raster.data, image)


@pytest.mark.parametrize(
    "image, ext",
    [
        (np.zeros((5, 6), np.uint16), ".pgm"),
        (np.zeros((5, 6), np.uint16), ".png"),
        (np.zeros((5, 6, 3), np.uint16), ".ppm"),
        (np.zeros((5, 6), np.uint16), ".tiff"),
        (np.zeros((5, 6, 3), np.uint16), ".png"),
        (np.zeros((5, 6, 3), np.uint8), ".bmp"),
        (np.zeros((5, 6, 3), np.uint8), ".jpg"),
    ],
)
def test_probe_accepts_every_supported_kind(image, ext):
    data = cv2.imencode(ext, image)[1].tobytes()
    assert probe_image(data) == (6, 5)
    assert read_image(data).shape == image.shape


@pytest.mark.parametrize("kind", ["TGA", "PCX", "GIF", "WEBP", "ICO"])
def test_probe_refuses_other_formats_pillow_knows(kind):
    buffer = io.BytesIO()
    Image.new("RGB", (40, 30)).save(buffer, kind)
    with pytest.raises(UnsupportedMediaError, match="not a supported image"):
        probe_image(buffer.getvalue())


def test_probe_checks_structure_without_decoding():
    img = np.random.default_rng(0).integers(0, 255, (60, 80), dtype=np.uint8)
    png = encode_png(img)
    assert probe_image(png, max_pixels=4800) == (80, 60)
    with pytest.raises(ImageTooLargeError):
        probe_image(png, max_pixels=4799)
    for broken in (png[:-30], _damage_idat(png, fix_crc=False)):
        with pytest.raises(UnsupportedMediaError, match="truncated or damaged"):
            probe_image(broken)
    # Right CRCs around pixel data that does not inflate: only decoding can tell.
    undecodable = _damage_idat(png, fix_crc=True)
    assert probe_image(undecodable) == (80, 60)
    with pytest.raises(UnsupportedMediaError, match="could not be decoded"):
        read_image(undecodable)


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=300), st.text(max_size=300)))
def test_any_points_file_parses_or_is_an_input_error(data):
    try:
        ref, mov = load_points(data)
    except InputError:
        return
    assert ref.shape == mov.shape and ref.ndim == 2 and ref.shape[1] == 2
