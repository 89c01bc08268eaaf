"""The synthetic actor with a nonlinear truth, its head-mounted-camera footage, marker layout design."""
