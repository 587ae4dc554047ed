"""The 3D view of the bench's robot (issue 8): kinematics (counts -> angles/pose), the viser
scene run by the appliance, and the per-run telemetry recording used for replay."""
