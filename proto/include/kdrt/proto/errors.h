#pragma once
/// Fixed phrases that proto error messages are built from. Messages add the location and the
/// values ("line 12: face index 40000 out of range (mesh has 37706 vertices)"); tests and callers
/// match on these phrases instead of copying literal text.

#include <string_view>

namespace kdrt::proto::errors {

// Mesh parsing (ParseError::message).
inline constexpr std::string_view kUnexpectedEnd = "unexpected end of file";
inline constexpr std::string_view kNotANumber = "is not a number";
inline constexpr std::string_view kNotAnInteger = "is not an integer";
inline constexpr std::string_view kNumberOutOfRange = "does not fit";
inline constexpr std::string_view kNonFinite = "is not finite";
inline constexpr std::string_view kIndexOutOfRange = "out of range";
inline constexpr std::string_view kUndefinedVertex = "not defined yet";
inline constexpr std::string_view kTooFewCorners = "needs at least 3 vertices";
inline constexpr std::string_view kTooManyCorners = "polygon vertex limit";
inline constexpr std::string_view kLimitExceeded = "exceeds the limit";
inline constexpr std::string_view kTrailingData = "unexpected data after";
inline constexpr std::string_view kMissingCoordinate = "needs 3 coordinates";
inline constexpr std::string_view kUnknownStatement = "unknown statement";
inline constexpr std::string_view kBadHeader = "bad header";
inline constexpr std::string_view kUnknownPlyFormat = "unknown PLY format";
inline constexpr std::string_view kUnknownPlyType = "unknown PLY type";
inline constexpr std::string_view kMissingProperty = "has no property";
inline constexpr std::string_view kMissingEndHeader = "missing end_header";
inline constexpr std::string_view kUnexpectedToken = "expected";
inline constexpr std::string_view kSizeMismatch = "but the file has";
inline constexpr std::string_view kTruncated = "file ends inside";
inline constexpr std::string_view kUnknownExtension = "cannot tell the mesh format";

}  // namespace kdrt::proto::errors
