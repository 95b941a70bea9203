"""Light from video: decode a clip, track its faces, and estimate one light per window of frames.

Modules: :mod:`f2l.video.decode` (frames, upright, with their times), :mod:`f2l.video.track`
(faces followed from frame to frame, one identity per person), :mod:`f2l.video.head` (a person's
head fitted once, its transport cached in the head's frame), :mod:`f2l.video.estimate` (a sliding
window of frames under one light, restarted at cuts and sudden changes).
"""
