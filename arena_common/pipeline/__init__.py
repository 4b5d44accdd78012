"""The vision pipeline's shared stage: **where a pose is decimated** (:mod:`.vision`), run by the
downsampler service or by the frame transform itself."""
