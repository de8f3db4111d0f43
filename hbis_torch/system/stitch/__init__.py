"""Stitching the nine views into a panorama, refining the homographies from the images, and the
FOV extension ratio measured on the result."""
