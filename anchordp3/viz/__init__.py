"""Pictures for people: camera mosaics, point clouds, curves. numpy + PIL/matplotlib only."""
