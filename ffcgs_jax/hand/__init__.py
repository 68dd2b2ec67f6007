"""The hand: its spec (joints, coupling, fingertips, collision spheres), MJX forward kinematics and the shipped
hands' assets."""
