"""stg-view: an interactive viewer in the browser, built on viser (the optional `viewer` extra).

The modules split what needs viser from what does not, so that the conventions and the render callback
are tested without a browser:

- `camera`: a viser camera (pose, field of view, canvas size) <-> our `stg_runtime.Camera`;
- `frames`: the render callback (a view, a time and a render mode -> the image sent to a browser);
- `playback`: the clock behind the time slider (play, pause, loop, speed, across segments);
- `keyframes`: a camera path interpolated between keyframes, as `stg-render --path` reads it;
- `server`: the viser application (imports viser): `Viewer`, `serve`;
- `cli`: `stg-view`.

Nothing here is imported by `import stg_runtime` or by the `Player`; viser is imported only by
`server` (tests/test_imports.py checks both).
"""
