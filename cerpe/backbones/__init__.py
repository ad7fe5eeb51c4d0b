"""Models behind the plug-in protocols of :mod:`cerpe.protocols`.

Import concrete modules directly (``cerpe.backbones.xfeat``, ``.offline``...) or
build the plug-ins of a :class:`cerpe.backbones.config.BackboneConfig` with
:func:`cerpe.backbones.build.build_plugins`; this
package imports nothing heavy itself so ``cerpe --help`` stays instant.
"""
