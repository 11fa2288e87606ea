"""Every error class of the API over real HTTP: status code and RFC 9457 problem document, and
no 500 for any input."""

from __future__ import annotations

import json
import socket
import zlib
from typing import Any
from urllib.parse import quote

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.service.helpers import (
    Pair,
    Server,
    assert_problem,
    png_file,
    submit,
    wait_for,
)

MAX_UPLOAD = 400 * 1024  # PWLREG_MAX_UPLOAD_BYTES of the test servers
MAX_PIXELS = 500_000  # PWLREG_MAX_PIXELS of the test servers


def _files(pair: Pair, **override: Any) -> dict[str, Any]:
    files: dict[str, Any] = {
        "reference": ("r.png", pair.reference_png, "image/png"),
        "moving": ("m.png", pair.moving_png, "image/png"),
        "points": ("p.json", pair.points_json, "application/json"),
    }
    for name, value in override.items():
        if value is None:
            files.pop(name, None)
        else:
            files[name] = (name, value, "application/octet-stream")
    return files


def png_bomb(width: int, height: int) -> bytes:
    """A PNG whose header announces ``width x height`` grey pixels with a tiny payload (the
    first rows of zeros): the header alone must get it refused, a decoder that trusted it would
    allocate ``width * height`` bytes."""
    return png_file(width, height, zlib.compress(b"\0" * (width + 1) * 16, 9))


# --- media and size ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "content"),
    [
        ("reference", b"this is not an image"),
        ("moving", b""),
        ("moving", b"%PDF-1.4\n" + bytes(range(256)) * 4),
    ],
)
def test_non_image_file_is_415(server: Server, pair: Pair, field: str, content: bytes) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, **{field: content}))
    doc = assert_problem(response, 415, field=field)
    assert doc["type"] == "urn:pwlreg:problem:unsupported-media-type"


@pytest.mark.parametrize("cut", [300, -100])
def test_truncated_image_is_refused_as_unsupported(server: Server, pair: Pair, cut: int) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, reference=pair.reference_png[:cut]))
    assert_problem(response, 415, field="reference")


def test_damaged_image_is_refused_as_unsupported(server: Server, pair: Pair) -> None:
    damaged = bytearray(pair.moving_png)
    damaged[len(damaged) // 2] ^= 0xFF  # inside the pixel data: a chunk's CRC no longer holds
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, moving=bytes(damaged)))
    doc = assert_problem(response, 415, field="moving")
    assert "damaged" in doc["detail"]


def test_pixels_that_do_not_decode_fail_the_job_with_the_reason(
    server: Server, pair: Pair
) -> None:
    # Sound structure (the API only checks that, without decoding) but no valid zlib stream:
    # the worker finds it and the job fails naming the file; the service goes on.
    broken = png_file(64, 48, b"\x78\x01" + bytes(range(256)) * 4)
    with server.client() as client:
        # No points: they would lie outside this small image, refused at submission.
        response = client.post("/v1/jobs", files=_files(pair, reference=broken, points=None))
        assert response.status_code == 201
        job = wait_for(client, response.json()["id"])
        assert job["status"] == "failed"
        assert job["error"]["field"] == "reference"
        assert "could not be decoded" in job["error"]["detail"]
        assert_problem(client.get(f"/v1/jobs/{job['id']}/mesh"), 409)
        good = submit(client, pair).json()["id"]
        assert wait_for(client, good, lambda j: j["status"] == "successful")


def test_body_that_is_not_multipart_is_415(server: Server) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", json={"reference": "r.png"})
        assert_problem(response, 415)
        response = client.post("/v1/jobs", content=b"", headers={"content-type": "image/png"})
        assert_problem(response, 415)


def test_decompression_bomb_is_refused_before_decoding(server: Server, pair: Pair) -> None:
    bomb = png_bomb(30_000, 30_000)  # 900 megapixels announced in a file of a few KB
    assert len(bomb) < 10_000
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, moving=bomb))
        doc = assert_problem(response, 422, field="moving")
        assert doc["type"] == "urn:pwlreg:problem:image-too-large"
        assert "900000000" in doc["detail"]
        # The server is fine afterwards (it did not try to allocate 900 MB).
        assert client.get("/healthz").status_code == 200


def test_real_image_over_the_pixel_limit_is_422(server: Server, pair: Pair) -> None:
    big = cv2.imencode(".png", np.zeros((600, 1000), np.uint8))[1].tobytes()  # 600k pixels
    assert len(big) < MAX_UPLOAD
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, reference=big))
    doc = assert_problem(response, 422, field="reference")
    assert doc["type"] == "urn:pwlreg:problem:image-too-large"
    assert str(MAX_PIXELS) in doc["detail"]


@pytest.mark.parametrize(
    ("image", "ext", "detail"),
    [(np.zeros((1, 50), np.uint16), ".tiff", "too small"),
     (np.zeros((1, 50), np.uint8), ".png", "too small")],
)
def test_image_the_registration_cannot_use_is_422_at_submission(
    server: Server, pair: Pair, image: np.ndarray, ext: str, detail: str
) -> None:
    with server.client() as client:
        response = client.post(
            "/v1/jobs", files=_files(pair, moving=cv2.imencode(ext, image)[1].tobytes())
        )
    doc = assert_problem(response, 422, field="moving")
    assert detail in doc["detail"]


def test_part_over_the_upload_limit_is_413_while_streaming(server: Server, pair: Pair) -> None:
    oversized = np.random.default_rng(0).bytes(MAX_UPLOAD + 50_000)
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, moving=oversized))
        doc = assert_problem(response, 413, field="moving")
        assert str(MAX_UPLOAD) in doc["detail"]
        # Nothing of the refused request stays in the staging area.
        assert not any((server.data_dir / "uploads").iterdir())


def test_chunked_upload_over_the_limit_is_413(server: Server, pair: Pair) -> None:
    boundary = "b0undary"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="reference"; filename="r.png"\r\n'
        "Content-Type: image/png\r\n\r\n"
    ).encode()

    def body():  # a generator body is sent chunked, without Content-Length
        yield head
        for _ in range(10):
            yield b"\0" * (MAX_UPLOAD // 5)
        yield f"\r\n--{boundary}--\r\n".encode()

    with server.client() as client:
        response = client.post(
            "/v1/jobs", content=body(),
            headers={"content-type": f"multipart/form-data; boundary={boundary}"},
        )
    assert_problem(response, 413, field="reference")


def test_declared_length_over_the_limit_is_413_at_once(server: Server) -> None:
    # A raw request announcing a terabyte: refused from its headers, body never read.
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(
            b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\n"
            b"Content-Type: multipart/form-data; boundary=x\r\n"
            b"Content-Length: 1000000000000\r\n\r\n--x\r\n"
        )
        answer = b""
        while b"\r\n\r\n" not in answer or not answer.rstrip().endswith(b"}"):
            data = sock.recv(65536)
            if not data:
                break
            answer += data
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"application/problem+json" in head.lower()
    doc = json.loads(body)
    assert doc["status"] == 413 and doc["type"] == "urn:pwlreg:problem:upload-too-large"


# --- form, options, points -------------------------------------------------------------------


@pytest.mark.parametrize("missing", ["reference", "moving"])
def test_missing_file_part_is_422(server: Server, pair: Pair, missing: str) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, **{missing: None}))
    assert_problem(response, 422, field=missing)


def test_unknown_or_repeated_part_is_422(server: Server, pair: Pair) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair), data={"colour": "blue"})
        assert_problem(response, 422, field="colour")
        files = list(_files(pair).items()) + [("moving", ("m2.png", pair.moving_png))]
        response = client.post("/v1/jobs", files=files)
        assert_problem(response, 422, field="moving")


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ("{not json", "options"),
        ("[1, 2]", "options"),
        ('{"bins": 1}', "options.bins"),
        ('{"bins": "many"}', "options.bins"),
        ('{"cost": "entropy"}', "options.cost"),
        ('{"colour": "blue"}', "options.colour"),
        ('{"epsilon": -0.5, "bins": 1000}', "options.epsilon"),
        ('{"max_points": 3}', "options.max_points"),
    ],
)
def test_invalid_options_are_422_with_the_field(
    server: Server, pair: Pair, options: str, field: str
) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair), data={"options": options})
    doc = assert_problem(response, 422, field=field)
    assert doc["type"] == "urn:pwlreg:problem:invalid-input"


def test_all_wrong_options_are_listed(server: Server, pair: Pair) -> None:
    with server.client() as client:
        response = client.post(
            "/v1/jobs", files=_files(pair), data={"options": '{"epsilon": -1, "bins": 1000}'}
        )
    doc = assert_problem(response, 422)
    assert {e["field"] for e in doc["errors"]} == {"options.epsilon", "options.bins"}


@pytest.mark.parametrize(
    "points",
    [
        b"{not json",
        b'{"reference": [[1, 2]]}',
        b'{"reference": [[1, 2], [3, 4]], "moving": [[1, 2]]}',
        b"a,b,c,d\n1,2,3,4\n",
        b"x,y,x_moving,y_moving\n1,2,three,4\n",
        b'{"reference": [[1, "nan"]], "moving": [[1, 2]]}',
    ],
)
def test_invalid_points_are_422(server: Server, pair: Pair, points: bytes) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, points=points))
    assert response.status_code == 422, response.text
    field = response.json()["field"]
    assert_problem(response, 422, field=field)
    assert field == "points" or field.startswith("points."), field


@pytest.mark.parametrize(
    ("content_type", "body"),
    [
        ("multipart/form-data", b"--x\r\n"),  # no boundary parameter
        ("multipart/form-data; boundary=x", b"garbage without any boundary"),
        ("multipart/form-data; boundary=x", b""),
        ("multipart/form-data; boundary=x",
         b'--x\r\nContent-Disposition: form-data; name="reference"\r\n\r\nabc'),  # cut off
        ("multipart/form-data; boundary=x",
         b"--x\r\nContent-Disposition: form-data\r\n\r\nabc\r\n--x--\r\n"),  # no name
        ("multipart/form-data; boundary=x",
         b"--x\r\nContent-Type: text/plain\r\n\r\nabc\r\n--x--\r\n"),  # no disposition
        ("multipart/form-data; boundary=" + "x" * 100, b"--" + b"x" * 100 + b"--\r\n"),
    ],
)
def test_malformed_multipart_is_a_4xx_problem(
    server: Server, content_type: str, body: bytes
) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", content=body, headers={"content-type": content_type})
    assert 400 <= response.status_code < 500, response.text
    assert_problem(response, response.status_code)


# --- resources, parameters, headers -------------------------------------------------------------


def test_unknown_job_is_404_everywhere(server: Server) -> None:
    with server.client() as client:
        for method, path in [
            ("GET", "/v1/jobs/0123456789abcdef0123456789abcdef"),
            ("DELETE", "/v1/jobs/0123456789abcdef0123456789abcdef"),
            ("GET", "/v1/jobs/nope/mesh"),
            ("GET", "/v1/jobs/nope/registered.png"),
            ("GET", "/v1/jobs/nope/convergence"),
            ("GET", "/v1/jobs/%27%3B%20DROP%20TABLE%20jobs%3B--"),
            ("GET", "/v2/anything"),
        ]:
            assert_problem(client.request(method, path), 404)


def test_wrong_method_is_405_with_allow(server: Server) -> None:
    with server.client() as client:
        response = client.put("/v1/jobs")
    assert_problem(response, 405)
    assert "POST" in response.headers["allow"]


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"limit": 0}, "limit"),
        ({"limit": "many"}, "limit"),
        ({"offset": -1}, "offset"),
        ({"offset": 58300861751105503232}, "offset"),  # past SQLite's integers (schemathesis)
        ({"status": "finished"}, "status"),
    ],
)
def test_bad_query_parameter_is_422(server: Server, params: dict, field: str) -> None:
    with server.client() as client:
        response = client.get("/v1/jobs", params=params)
    assert_problem(response, 422, field=field)


@pytest.mark.parametrize("key", [b"has space", b"x" * 256, "caf\u00e9".encode()])
def test_bad_idempotency_key_is_422(server: Server, pair: Pair, key: bytes) -> None:
    with server.client() as client:
        response = submit(client, pair, headers={"Idempotency-Key": key})  # type: ignore[dict-item]
    assert_problem(response, 422, field="Idempotency-Key")


# --- no input produces a 500 -----------------------------------------------------------------


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    part=st.sampled_from(["reference", "moving", "points", "options"]),
    content=st.one_of(
        st.binary(max_size=2048),
        st.text(max_size=200).map(str.encode),
        st.sampled_from([b"{}", b"[]", b"null", b"{\"reference\": []}", b"x,y\n",
                         b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff\xe0", b"II*\x00", b"P5\n2 2\n255\n"]),
    ),
)
def test_random_parts_never_cause_a_server_error(
    server: Server, pair: Pair, part: str, content: bytes
) -> None:
    with server.client() as client:
        response = client.post("/v1/jobs", files=_files(pair, **{part: content}))
        if response.status_code == 201:  # a valid request after all: leave no work behind
            client.delete(response.headers["location"])
            return
    assert 400 <= response.status_code < 500, response.text
    assert response.headers["content-type"].startswith("application/problem+json")


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    query=st.dictionaries(
        st.sampled_from(["limit", "offset", "status"]),
        st.one_of(
            st.integers(min_value=-(2**70), max_value=2**70).map(str),
            st.sampled_from([2**31, 2**53, 2**63 - 1, 2**63, 2**64 + 5, -(2**63) - 1]).map(str),
            st.text(max_size=20),
            st.sampled_from(["accepted", "running", "1e3", ""]),
        ),
    ),
    job_id=st.text(max_size=40).filter(lambda s: "/" not in s and s not in (".", "..")),
)
def test_random_queries_and_ids_never_cause_a_server_error(
    server: Server, query: dict, job_id: str
) -> None:
    with server.client() as client:
        listed = client.get("/v1/jobs", params=query)
        assert listed.status_code in (200, 422), listed.text
        for path in ("", "/mesh", "/registered.png", "/convergence"):
            response = client.get(f"/v1/jobs/{quote(job_id, safe='')}{path}")
            assert response.status_code < 500, response.text


DEEP = "[" * 3000 + "]" * 3000  # past the JSON decoder's recursion limit


def test_json_nested_past_the_decoder_is_a_4xx_problem(server: Server, pair: Pair) -> None:
    with server.client() as client:
        options = client.post("/v1/jobs", files=_files(pair), data={"options": f'{{"a": {DEEP}}}'})
        subscriber = client.post("/v1/jobs", files=_files(pair),
                                 data={"subscriber": f'{{"successUri": {DEEP}}}'})
        execute = client.post("/processes/pwl-registration/execution",
                              content=f'{{"inputs": {DEEP}}}'.encode(),
                              headers={"Content-Type": "application/json"})
    assert "nested too deeply" in assert_problem(options, 422, field="options")["detail"]
    assert "nested too deeply" in assert_problem(subscriber, 422, field="subscriber")["detail"]
    assert "nested too deeply" in assert_problem(execute, 400)["detail"]
