"""Options of one registration: the single declaration the CLI, the API and ``/v1/options`` use."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class RegistrationOptions(BaseModel):
    """Every tunable of a registration job, with defaults and bounds.

    Units: distances in pixels of the reference image, areas in square pixels, similarity
    thresholds in NMI (dimensionless, bits / bits) or NCC units.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- mesh optimization -------------------------------------------------------------------
    optimizer: Literal["none", "greedy", "morris-kanade", "nakatuji"] = Field(
        "greedy",
        description="Mesh optimizer: 'greedy' is the paper's edge-swap search (Algorithm 1); "
        "'none' keeps the Delaunay mesh; 'morris-kanade' and 'nakatuji' are the baselines the "
        "paper compares against.",
    )
    cost: Literal["mi", "ncc"] = Field(
        "mi",
        description="Consistency measure ranking the swaps of the greedy search: normalised "
        "mutual information ('mi', the paper) or normalised cross-correlation ('ncc').",
    )
    epsilon: float = Field(
        0.01,
        ge=0.0,
        le=1.0,
        description="A swap is accepted only if it raises the quad's consistency by more than "
        "this (NMI or NCC units). The paper measured |delta| < 0.008 on planar quads.",
    )
    bins: int = Field(
        16, ge=2, le=256, description="Grey-level bins per image of the joint histogram (M)."
    )
    min_triangle_area: float = Field(
        25.0,
        ge=0.0,
        le=1e7,
        description="Initial triangles whose reference area is below this (square pixels) are "
        "discarded: a 16x16-bin joint histogram of fewer than about 25 pixels per triangle "
        "(50 per quad) is dominated by sampling noise, and such slivers carry unstable affine "
        "maps.",
    )
    max_iterations: int = Field(
        100_000, ge=0, le=10_000_000, description="Upper bound on accepted swaps."
    )
    seed: int = Field(
        0,
        ge=0,
        le=2**31 - 1,
        description="Seed of every random choice (robust estimation, "
        "random search); the same input and seed give the same result.",
    )

    # --- conjugate points (matching and epipolar filter) ---------------------------------------
    matcher: Literal["lk", "sift", "auto"] = Field(
        "auto",
        description="Automatic matcher used when no points are given: Harris + pyramidal "
        "Lucas-Kanade ('lk', the paper), SIFT with ratio and mutual checks ('sift'), or 'auto' "
        "(tracking first, SIFT when too few consistent pairs survive).",
    )
    epipolar_model: Literal["affine", "projective"] = Field(
        "affine",
        description="Model of the robust epipolar filter: the affine fundamental matrix of the "
        "paper or the projective fundamental matrix (close-range perspective photos).",
    )
    epipolar_filter: bool = Field(
        True,
        description="Reject point pairs inconsistent with the epipolar geometry (also "
        "applied to points sent by the client).",
    )
    epipolar_threshold: float = Field(
        1.5,
        gt=0.0,
        le=100.0,
        description="Inlier threshold of the epipolar filter: Gold Standard (affine) or Sampson "
        "(projective) distance in pixels.",
    )
    max_points: int = Field(
        1000, ge=3, le=20_000, description="Target number of automatically matched points."
    )
    min_distance: float = Field(
        10.0,
        ge=0.0,
        le=10_000.0,
        description="Minimum distance between automatically matched points in the reference "
        "image (pixels), so that the points spread over the overlap.",
    )
