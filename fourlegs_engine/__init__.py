"""4-LEGS highlights engine: pure Python + torch + numpy (never imports bpy).

Data flows one way: scene -> render -> language -> query -> highlights.
"""
__version__ = "0.1.0"
