"""4-LEGS highlights engine: pure Python + torch + numpy (never imports bpy).

Data flows one way: scene -> render -> language (fit, cluster) -> demo -> query -> highlights -> pipeline
-> highlight_job, api -> commands (docs/CONTRACTS.md; tests/test_architecture.py holds it).
"""
__version__ = "0.1.0"
