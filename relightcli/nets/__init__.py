"""ONNX Runtime sessions: one base (`session.ModelSession`) and one small class per model family
doing only pre/post-processing. Import the family classes from their modules."""
