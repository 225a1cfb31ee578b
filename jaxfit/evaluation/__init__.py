"""The thesis's evaluation: synthetic models and clouds (``synthetic``), its four
scenarios (``scenarios``), error measures (``measures``), the plain NumPy reference
implementation (``reference``) and the experiment runner (``evaluate``). Nothing here is
imported by ``import jaxfit``; import the module you need."""
