"""Data parsers: every format becomes one `SceneData` (see `base.parse_scene`)."""
