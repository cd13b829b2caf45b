"""Side panels of the editor, one module each; every `draw(app)` reads and edits `app.state`."""
