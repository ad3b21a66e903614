"""Body-model files: SMPL model files and AMASS-style SMPL motions, read into plain arrays."""
