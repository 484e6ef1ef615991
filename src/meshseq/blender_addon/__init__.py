"""The Blender add-on of meshseq, as package data: ``addon.py`` (the add-on, it needs ``bpy``) and
``cachefiles.py`` (its plain-Python file readers and writers).

``meshseq blender-addon`` packs them into an installable zip as the package ``meshseq_blender``
(``addon.py`` becoming its ``__init__.py``). meshseq never imports ``addon.py``.
"""
