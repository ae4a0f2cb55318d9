"""SEM tilt-series photogrammetry under parallel projection (the seed paper's section 3).

Modules: `parallax` (the eucentric-tilt camera model and heights from the parallax of one image pair),
`affine` (the affine fundamental matrix used to verify matches), `factorization` (Tomasi-Kanade with a metric
upgrade that estimates tilts and axis, then a least-squares adjustment of all observations), `icp` (merging the
per-pair point sets), `heightmap` (gridding, spike removal, scoring against ground truth), `dense` (multi-view
least-squares heights at every pixel), `rectified` (stereo matching of rectified tilt pairs) and `pipeline` (the
`mvrecon sem` run).
"""
