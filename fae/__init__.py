"""fae: an MPEG-4 Facial Animation engine.

Data flow (each package imports only the ones before it):
``mpeg4 -> io -> adapt / anatomy -> sim -> animate -> render / net -> commands -> cli``.
"""

__version__ = "0.1.0"
