# Sourced by scripts/demo and scripts/test: offscreen rendering through EGL, no display needed.
export VTK_DEFAULT_OPENGL_WINDOW="${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}"
export PYVISTA_OFF_SCREEN=true
