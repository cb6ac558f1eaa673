"""slam service: marker SLAM over TagPoses; publishes camera poses and the tag map; writes TUM files."""
