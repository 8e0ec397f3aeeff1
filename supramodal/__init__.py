"""The supramodal texture model of Bernard et al. (2010), streaming from the first line.

Pure numpy/scipy: no devices, no threads, no knowledge of the node. Blocks:

* :mod:`supramodal.banks`: cochlea and whisker filterbanks as data.
* :mod:`supramodal.gammatone`: exact streaming gammatone filterbank.
* :mod:`supramodal.peaks`: streaming peak extractor.
* :mod:`supramodal.features`: A, f, Af accumulated over windows.
* :mod:`supramodal.pipeline`: the three above chained, block in, windows out.
* :mod:`supramodal.mlp`: multilayer perceptron trained with iRPROP-.
* :mod:`supramodal.model`: a trained classifier with its metadata, saved as data.
* :mod:`supramodal.textures`: three-peak texture synthesis and texture-set files.
"""

__version__ = "0.1.0"
