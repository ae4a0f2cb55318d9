"""The seed paper's two-view stereo: rectification, disparity (gee, sgbm, best), evaluation, depth, figures."""
