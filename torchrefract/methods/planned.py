"""Methods of the design not implemented yet (registry entries that raise on render)."""

from torchrefract.methods.base import Planned

LEAN = Planned("lean", "Dai and Wyman 2012, issue #24")
GSR = Planned("gsr", "Dai and Wyman 2012, issue #24")
SH = Planned("sh", "Genevaux et al. 2006, issue #25")
