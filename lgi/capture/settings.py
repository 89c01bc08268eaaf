"""The tracker's defaults, written once: the library's tracker (:class:`lgi.capture.tracking.TrackOptions`,
:class:`lgi.capture.dots.DotOptions`) and ``lgi track``'s options read them. No heavy import here: the command
line's parser reads them."""

#: The dot detector's centre error per image coordinate (px, one standard deviation), which sets each bundle's
#: covariance (:func:`lgi.capture.camera.triangulation_covariance`). Measured on ``lgi synth --hmc`` footage (1280x1024
#: fisheye, 9 px dots, 0.3 px paint jitter, sensor noise and blur): the detected centres of 12,588 visible dots
#: (60 frames, both cameras) against their true projections, RMS 0.22 px in x, 0.27 px in y, 0.24 px over both
#: (robust spread 0.18 / 0.26 px).
PIXEL_NOISE_PX = 0.25
#: px: how far from its predicted position a dot is searched for in the next frame.
GATE_PX = 12.0
#: px: the painted dots' typical diameter in the images (:meth:`lgi.capture.dots.DotOptions.for_size`).
DOT_SIZE_PX = 9.0
