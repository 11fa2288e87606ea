"""Options of one registration: the single declaration the CLI, the API and ``/v1/options`` use."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class RegistrationOptions(BaseModel):
    """Every tunable of a registration job, with defaults and bounds.

    Units: distances in pixels of the reference image, areas in square pixels, similarity
    thresholds in NMI (dimensionless, bits / bits) or NCC units.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- mesh optimization -------------------------------------------------------------------
    optimizer: Literal["none", "greedy", "greedy-pyramid", "morris-kanade", "nakatuji"] = Field(
        "greedy",
        description="Mesh optimizer: 'greedy' is the paper's edge-swap search (Algorithm 1); "
        "'greedy-pyramid' runs it on images blurred by 3 px, then 1 px, then sharp (MI still "
        "ranks the diagonals of quads misregistered beyond their texture scale; measured with "
        "true points: mean endpoint error 3.56 px against 3.70 on the synthetic suite and "
        "1.009 against 1.024 px on Middlebury, for about three times the search time); 'none' "
        "keeps the Delaunay mesh; 'morris-kanade' and 'nakatuji' are the baselines the paper "
        "compares against.",
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
    epsilon_pixels: float = Field(
        250.0,
        ge=0.0,
        le=1e7,
        description="Quad size (reference pixels) at which a swap must gain more than "
        "epsilon; the threshold of a quad of n pixels is epsilon * sqrt(epsilon_pixels / n) "
        "(the noise of an MI estimate falls as one over the square root of its sample), within "
        "epsilon/2 and 5 epsilon, and swaps go in order of their gain over it. 0 keeps the "
        "paper's one epsilon for every quad. Measured with true points (default against 0): "
        "synthetic mean endpoint error 3.58 against 3.70 px (median reduction against Delaunay "
        "35.2 % against 32.0 %, no case more than 2 % worse), Middlebury 1.020 against 1.024 px.",
    )
    insert_vertices: Literal["automatic", "always", "never"] = Field(
        "automatic",
        description="Vertex insertion guided by the mesh: the moving image resampled by a first "
        "mesh differs from the reference only by the mesh's residual error, which a dense "
        "optical flow measures well; reference corners away from the vertices where that flow "
        "is consistent and the correlation check confirms it become new pairs; where the "
        "mesh is too far off for the flow, corners are searched for along their epipolar "
        "line (unambiguous peak, left-right check, not contradicted by their neighbours). "
        "Large corrections must also raise the mutual information of the triangle they "
        "split; at most as many new pairs as matched ones (at least 200). Where the residual "
        "flow jumps (a depth step inside a triangle), points on both sides of the jump are "
        "searched for along their epipolar lines too, up to half the matched pairs more. The "
        "mesh is built again over all of them, its matched and inserted pairs (never the "
        "client's) each moved by at most 1.5 px where an affine fit of its 31 px window "
        "(the enhanced correlation coefficient) takes it, on one surface, correlating at 0.9 "
        "or more, within the epipolar threshold and folding no triangle. After the swaps, a "
        "measured vertex that the images contradict (its triangles gain more than twice the "
        "swaps' threshold when it moves as at least two of its neighbours do) is moved so (the "
        "'correct' move), and with "
        "extent='frame' each extrapolated border vertex is searched for along its epipolar "
        "line around its extrapolations, moved where its triangles gain as much (the 'border' "
        "move). Last, every vertex but the client's moves together, by at most 2 px, so that "
        "the images agree through the mesh over all its pixels (a direct photometric "
        "alignment), kept where its triangles' consistency does not fall (the 'align' move); "
        "a measured inner vertex whose triangles, filled again without it, gain as much as a "
        "'correct' move must leaves the mesh (the 'remove' move: a T-junction, or a vertex "
        "whose triangles reach over a depth step); then the optimizer runs once more over the "
        "moved mesh. On this path the swaps look at the images reduced to at most 640 px a "
        "side, as the verdict does. "
        "'automatic': only when the service found the points; 'always': also refine client "
        "points (which are kept, never moved); 'never': the paper's mesh over the points "
        "alone.",
    )
    lookahead: bool = Field(
        True,
        description="When no single swap gains enough, also try two swaps in a row (an edge, "
        "then one of its quad's edges) scored together over the pentagon they change, and keep "
        "the pair if it gains more than that pentagon's threshold. False is the paper's search. "
        "Measured against a swap search told the true error (python -m bench.beyond): with "
        "true points it realises a median 0.91 of the achievable gain on 42 synthetic scenes "
        "(0.85 without, 0.81 with the paper's settings), for about twice the optimizing time.",
    )
    bins: int = Field(
        16,
        ge=2,
        le=256,
        description="Grey-level bins per image of the joint histograms the optimizer ranks "
        "swaps by (M, as in the paper). 32 lowered the error on Middlebury with 150 true points "
        "(21.0 % below Delaunay against 17.4 %) but not on synthetic scenes, for 1.4 to 1.7 "
        "times the optimizing time.",
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

    extent: Literal["hull", "frame"] = Field(
        "frame",
        description="Area the mesh covers. 'hull': the convex hull of the conjugate points (the "
        "paper's mesh; pixels outside it stay transparent in registered.png). 'frame': the "
        "whole reference frame, with vertices added along its border whose moving positions "
        "are extrapolated by an affine map fitted to the 12 nearest pairs (weighted by "
        "distance, trimmed of pairs it misses); mesh.json marks them 'extrapolated' and the "
        "quality verdict counts their area apart. Default 'frame' because users overlaying or "
        "mosaicking a result expect the whole frame, as co-registration tools give it; with "
        "automatic points the hull misses 30-38 % of the Middlebury pixels that have a truth. "
        "Measured there (python -m bench.trust), the local affine model extrapolates those "
        "pixels with a mean error of 1.1-3.9 px against 2.2-6.6 px for one robust global "
        "homography.",
    )

    on_unreliable: Literal["succeed", "fail"] = Field(
        "succeed",
        description="What a result whose quality verdict is 'unreliable' does: 'succeed' "
        "returns it with the verdict and its reasons (mesh.json and the job's 'quality'); "
        "'fail' fails the job (CLI: exit status 3) with a problem document that gives the "
        "reasons, for pipelines that must never consume such a result.",
    )

    # --- input bands ---------------------------------------------------------------------------
    band: str = Field(
        "luminance",
        pattern=r"^(luminance|[1-9][0-9]{0,4})$",
        description="What matching and scoring look at in each image: 'luminance', or a band "
        "number from 1 (the file's band order: 1 is red in a colour image) taken from both "
        "images. 'luminance' of a grey or colour 8/16-bit image is its usual luminance (the "
        "registered.png keeps the colour); of a multi-band, float or masked raster (GeoTIFF) "
        "the mean of its bands after each is rescaled to its own range. Bands of rasters, and a "
        "chosen band, are rescaled to 8 bits from the 0.5 and 99.5 percentiles of their valid "
        "pixels; nodata, masked and NaN pixels are filled smoothly from their valid neighbours "
        "so that they give the matcher and the scoring no texture. registered.tif (for a "
        "georeferenced reference) always holds every band of the moving image at its own data "
        "type; registered.png shows what was matched. An integer is accepted as well as a "
        "string (2 is '2').",
    )

    @field_validator("band", mode="before")
    @classmethod
    def _band_number(cls, value: object) -> object:
        return str(value) if isinstance(value, int) and not isinstance(value, bool) else value

    # --- conjugate points (matching and epipolar filter) ---------------------------------------
    matcher: Literal["lk", "sift", "auto"] = Field(
        "auto",
        description="Automatic matcher used when no points are given: Harris corners tracked by "
        "pyramidal Lucas-Kanade with a forward-backward check ('lk', the paper's; a global "
        "homography tracked on a coarse level pre-aligns the images), SIFT with ratio and "
        "mutual checks ('sift', wide baseline), or 'auto': tracking first; if fewer than 100 "
        "tracked pairs (or fewer than half of the forward-backward consistent ones) pass the "
        "epipolar filter, SIFT runs, and tracking is retried from the homography of the SIFT "
        "matches; the largest consistent set wins and the result names its matcher.",
    )
    epipolar_model: Literal["affine", "projective"] = Field(
        "projective",
        description="Model of the robust epipolar filter: the affine fundamental matrix of the "
        "paper (MSAC, 4-pair samples) or the projective fundamental matrix (OpenCV USAC). "
        "Default 'projective', measured on the real pairs (python -m bench.matching): on the "
        "same Lucas-Kanade tracks of the three close-range Strecha pairs, the affine model "
        "accepts 31-37% of the pairs the projective one accepts (398/202/534 vs 1065/660/1447 "
        "epipolar inliers; 348/192/485 vs 955/621/1000 kept) with no gain in accuracy (median "
        "Sampson distance to the true F 0.14-0.23 px for both; 3.1% of the pairs the affine "
        "model keeps on herzjesu are over 3 px, none of the projective ones), because "
        "perspective moves true "
        "matches off the affine hyperplane by more than the threshold; on the near-affine pairs "
        "(Oxford leuven, Middlebury) both keep the same pairs. Choose 'affine' for distant, "
        "narrow-field views (the paper's model) or for 6 to 9 client pairs (it needs 6, the "
        "projective model 10).",
    )
    epipolar_filter: bool = Field(
        True,
        description="Reject point pairs inconsistent with the epipolar geometry (also "
        "applied to points sent by the client; a client's pair the filter cannot check, off "
        "the plane the others lie on or missing its neighbours' map by over 20 px, is kept "
        "and makes the verdict doubtful).",
    )
    epipolar_threshold: float = Field(
        1.5,
        gt=0.0,
        le=100.0,
        description="Inlier threshold of the epipolar filter in pixels: Gold Standard distance "
        "(affine: perpendicular distance to the hyperplane in (x', y', x, y)) or Sampson distance "
        "(projective), both joint displacements of the two points. 1.5 px is about 3 times the "
        "90th percentile of the tracked pairs' distance to the true F on the Strecha pairs "
        "(0.4-0.7 px).",
    )
    max_points: int = Field(
        1000,
        ge=10,
        le=20_000,
        description="Most automatically matched pairs kept (the spread step keeps the strongest "
        "of each grid cell first); at least 10, the pairs the projective epipolar filter "
        "needs (fewer always failed, as if the images shared no detail). 1000 vertices give "
        "about 2000 triangles, vertices about 80 px "
        "apart on a 3072x2048 image: dense enough to follow the planes of a building; every "
        "extra vertex adds about 3 edges to the MI search.",
    )
    min_distance: float = Field(
        10.0,
        ge=0.0,
        le=10_000.0,
        description="Minimum distance between automatically matched points in the reference "
        "image (pixels), so that they spread over the overlap instead of clustering on one "
        "textured patch. 10 px keeps triangles above about 40 square pixels (over "
        "min_triangle_area, enough pixels for a joint histogram) and the 21 px LK windows of "
        "neighbours from mostly overlapping.",
    )
