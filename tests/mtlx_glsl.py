"""The MaterialX check the export tests share: a document validated against the standard libraries, and the
GLSL pixel shader MaterialX generates for one of its materials."""


def validated_glsl(doc, material: str, name: str = "shader") -> str:
    """Import MaterialX's standard libraries into ``doc``, assert it validates, and return the GLSL pixel-stage
    source that MaterialX's GLSL generator writes for the material node ``material``."""
    import MaterialX as mx
    import MaterialX.PyMaterialXGenGlsl as mx_glsl
    import MaterialX.PyMaterialXGenShader as mx_gen

    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    doc.importLibrary(lib)
    ok, msg = doc.validate()
    assert ok, msg
    gen = mx_glsl.GlslShaderGenerator.create()
    ctx = mx_gen.GenContext(gen)
    ctx.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
    return gen.generate(name, doc.getNode(material), ctx).getSourceCode(mx_gen.PIXEL_STAGE)
