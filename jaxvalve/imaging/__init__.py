"""From a CT scan to an aortic root: the volume in patient coordinates (`volume`), a
synthetic patient-like scan with a known wall (`phantom`), the segmentation of the
contrast-filled root (`segment`) and its wall surface (`surface`).  Files (NIfTI, DICOM)
are read and written by `jaxvalve.io.volumes`."""
