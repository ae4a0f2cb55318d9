"""Image-quality degradation studies: degrade images, rerun both engines per level, find where each breaks."""
