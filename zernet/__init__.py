"""zernet: convolutional neural networks on curved surfaces via Zernike local tangent-space estimation.

Data flows one way: surface -> polar coordinates -> patch operator -> layers -> models -> training.
"""

__version__ = "0.2.0"
