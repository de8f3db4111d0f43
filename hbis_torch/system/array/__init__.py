"""The 3 x 3 camera array: its geometry, cameras, the wide planar scene, rendering and the
simulated device the foveation loop drives."""
