"""Vision front-end: marker segmentation of the image pairs and calibration of the camera rig."""
