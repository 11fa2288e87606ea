"""The results of a registration, declared once.

Each :class:`ResultFormat` names a file, its media type and its writer. The worker and the CLI
write the results from :data:`RESULTS`; the service's job links and result routes (and so the
OpenAPI document) are generated from it. Adding a result is one entry here.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pwlreg.core.io import convergence_document, encode_png, mesh_document

if TYPE_CHECKING:
    from pwlreg.core.pipeline import RegistrationResult


@dataclass(frozen=True)
class Sources:
    """What writers may need beyond the result: the decoded inputs, their files (for metadata
    such as georeferencing) and the threads to use."""

    reference: np.ndarray | None = None
    moving: np.ndarray | None = None
    reference_path: Path | None = None
    moving_path: Path | None = None
    threads: int = 1


Writer = Callable[["RegistrationResult", Sources, Path], None]


def _always(result: RegistrationResult, sources: Sources) -> bool:
    return True


@dataclass(frozen=True)
class ResultFormat:
    """One result file of a registration.

    Attributes
    ----------
    name : str
        Key of the result (in :func:`write_outputs`'s answer and the storage).
    filename : str
        File name in the results directory (and the download's name).
    route : str
        Last segment of the result's URL under ``/v1/jobs/{id}/``.
    media_type : str
        Its ``Content-Type``.
    title : str
        One line, used as the job link's title and the route's summary.
    description : str
        What the file holds (the route's description).
    write : callable
        ``write(result, sources, path)`` writes the file.
    applies : callable
        ``applies(result, sources)``: whether the result exists for this registration (a
        GeoTIFF only for a georeferenced reference, say). Absent results have no link.
    """

    name: str
    filename: str
    route: str
    media_type: str
    title: str
    description: str
    write: Writer
    applies: Callable[[RegistrationResult, Sources], bool] = _always


def _write_json(document: Callable[[RegistrationResult], dict], indent: int | None = None
                ) -> Writer:
    def write(result: RegistrationResult, sources: Sources, path: Path) -> None:
        path.write_text(json.dumps(document(result), indent=indent))
    return write


def _write_registered(result: RegistrationResult, sources: Sources, path: Path) -> None:
    path.write_bytes(encode_png(result.registered, threads=sources.threads))


RESULTS: dict[str, ResultFormat] = {
    r.name: r
    for r in (
        ResultFormat(
            "mesh", "mesh.json", "mesh", "application/json",
            "Meshes, swaps and matching results",
            "mesh.json: reference and moving vertices, initial and final triangles, the swaps, "
            "the parameters, the quality verdict and the matching results (pixel coordinates, x "
            "right, y down, (0, 0) the centre of the top-left pixel).",
            _write_json(mesh_document),
        ),
        ResultFormat(
            "registered", "registered.png", "registered.png", "image/png",
            "Moving image registered onto the reference (alpha = inside the mesh)",
            "The moving image warped onto the reference, PNG with alpha (opaque inside the "
            "mesh).",
            _write_registered,
        ),
        ResultFormat(
            "convergence", "convergence.json", "convergence", "application/json",
            "Consistency (MI, NMI) per iteration of the optimizer",
            "convergence.json: initial and final MI/NMI (bits, dimensionless), every iteration "
            "with its swap, delta, MI, NMI and elapsed seconds, and why it stopped.",
            _write_json(convergence_document, indent=1),
        ),
    )
}
"""Every result a registration can have, by name, in the order of the job links."""


def write_outputs(
    result: RegistrationResult,
    out_dir: str | os.PathLike,
    *,
    sources: Sources | None = None,
    threads: int = 1,
) -> dict[str, Path]:
    """Write every result that applies into ``out_dir``.

    Parameters
    ----------
    result : RegistrationResult
    out_dir : path
        Created if needed.
    sources : Sources, optional
        The decoded inputs, for results drawn on them; ``threads`` is used when omitted.
    threads : int
        Threads a writer may use (PNG compression).

    Returns
    -------
    dict
        The written files' paths by result name.
    """
    sources = sources or Sources(threads=threads)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for fmt in RESULTS.values():
        if fmt.applies(result, sources):
            path = out / fmt.filename
            fmt.write(result, sources, path)
            written[fmt.name] = path
    return written
