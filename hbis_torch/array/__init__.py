"""The HBIS as a whole: the 3 x 3 camera array, stitching, and two-stage foveation."""
