#pragma once
/// KDRR / KDRH / KDRO ray batches, all of it: the header and its limits (ray_batch_header.h), the
/// whole-body codecs (ray_batch_codec.h) and the incremental KDRR decoder (ray_stream_decoder.h).
/// Byte layouts and worked hex examples: proto/FORMATS.md.

#include "kdrt/proto/ray_batch_codec.h"
#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/ray_stream_decoder.h"
