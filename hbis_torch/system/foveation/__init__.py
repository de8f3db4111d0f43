"""The two-stage operation: motion detection, steering the fovea onto an object, and the loop."""
