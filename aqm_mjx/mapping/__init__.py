"""Stage 3, mapping: keypoint selection (``keypoints``), the keypoint graph (``graph``) and the map
stage that builds it from dataset states (``build``)."""
