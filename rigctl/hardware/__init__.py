"""Hardware facts as data: one row per device model, each table with its published source
cited beside it. The drivers, the planner and the exporters read these tables; the
stand-ins in ``rigctl.mocks`` keep their own transcription of the same sources."""
