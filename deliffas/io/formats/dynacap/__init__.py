"""DynaCap / Skeletool captures: character, skin, motion and segmentation files, skeletons, calibrations, meshes, frames."""
