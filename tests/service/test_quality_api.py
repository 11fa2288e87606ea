"""The quality verdict over HTTP and in the CLI: carried by the job and mesh.json, and
``on_unreliable=fail`` turning an unreliable result into a failed job or exit status 3."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from pwlreg.service.cli import UNRELIABLE_EXIT
from tests.service.helpers import Pair, Server, make_pair, submit, wait_for
from tests.service.test_cli import pwlreg


def _unrelated(pair: Pair) -> Pair:
    """The pair's reference and points with the moving image of another texture."""
    return replace(pair, moving_png=make_pair(seed=99).moving_png)


def test_successful_job_carries_the_verdict_and_mesh_json_its_scores(
    server: Server, pair: Pair
) -> None:
    with server.client() as client:
        done = wait_for(client, submit(client, pair).json()["id"])
        assert done["status"] == "successful", done
        quality = done["quality"]
        assert quality["verdict"] == "good", quality
        assert quality["reasons"] == []
        for key in ("points", "inlier_share", "measured_coverage", "mesh_coverage",
                    "mi_before", "mi_after", "global_peak", "low_consistency_share"):
            assert key in quality, key
        mesh = client.get(f"/v1/jobs/{done['id']}/mesh").json()
        assert mesh["quality"]["verdict"] == quality["verdict"]
        assert len(mesh["triangle_scores"]) == len(mesh["final_triangles"])
        assert len(mesh["extrapolated"]) == len(mesh["reference_vertices"])
        assert "quality" in done["message"] or quality["verdict"] in done["message"]


def test_unreliable_result_fails_the_job_when_asked(server: Server, pair: Pair) -> None:
    other = _unrelated(pair)
    with server.client() as client:
        kept = wait_for(client, submit(client, other).json()["id"])
        assert kept["status"] == "successful"
        assert kept["quality"]["verdict"] == "unreliable", kept["quality"]

        job = submit(client, other, options={"on_unreliable": "fail"}).json()
        done = wait_for(client, job["id"])
        assert done["status"] == "failed", done
        assert done["error"]["type"] == "urn:pwlreg:problem:unreliable-result"
        assert done["error"]["status"] == 422
        assert done["quality"]["verdict"] == "unreliable"
        assert done["quality"]["reasons"][0] in done["error"]["detail"]
        assert client.get(f"/v1/jobs/{job['id']}/mesh").status_code == 409  # no result


def test_cli_exits_with_3_on_an_unreliable_result(pair: Pair, tmp_path: Path) -> None:
    other = _unrelated(pair)
    paths = {}
    for name, data in (("reference.png", other.reference_png),
                       ("moving.png", other.moving_png), ("points.json", other.points_json)):
        paths[name] = tmp_path / name
        paths[name].write_bytes(data)
    args = ["register", str(paths["reference.png"]), str(paths["moving.png"]), "--points",
            str(paths["points.json"]), "--out", str(tmp_path / "out"), "-q"]
    run = pwlreg(*args, "--on-unreliable", "fail")
    assert run.returncode == UNRELIABLE_EXIT, run.stderr
    assert "unreliable" in run.stderr
    run = pwlreg(*args)
    assert run.returncode == 0, run.stderr
    assert "quality unreliable" in run.stdout


def test_a_pair_without_reliable_points_fails_with_an_unreliable_verdict(
    server: Server, pair: Pair
) -> None:
    """Unrelated images without points: the matcher finds nothing unambiguous, so the job fails
    and says why, with the verdict."""
    other = _unrelated(pair)
    with server.client() as client:
        done = wait_for(client, submit(client, other, points=None).json()["id"])
        assert done["status"] == "failed", done
        assert done["error"]["type"] == "urn:pwlreg:problem:registration-failed"
        assert done["quality"]["verdict"] == "unreliable"
        assert done["quality"]["reasons"] == [done["error"]["detail"].removeprefix("points: ")]
